"""The vehicle's physics: 6-DoF dynamics, the rate loop and mixer, the sensors, and what a
scenario randomises in them (airframe, wind, sensor faults)."""
