# visland — the two commands a newcomer needs are `make demo` and `make test`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup demo readme test test-slow lint bench wheel clean

$(STAMP): pyproject.toml Makefile
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	# torch first and pinned: the CPU build, never a CUDA download.
	$(BIN)/pip install --quiet torch==2.13.0
	$(BIN)/pip install --quiet -e '.[dev,ray]'
	# MAVProxy (the ground-station interop test) without its declared dependencies: they pull
	# opencv-python and vtk, which clash with opencv-python-headless; its core needs pymavlink
	# and pyserial (both in [dev]).
	$(BIN)/pip install --quiet --no-deps MAVProxy==1.8.75
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(BIN)/visland demo

# The README's demo picture and output block, from a real demo run of the shipped model.
readme: $(STAMP)
	$(BIN)/visland readme

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q

test-slow: $(STAMP)
	$(BIN)/python -m pytest -q -m slow

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

bench: $(STAMP)
	$(BIN)/visland bench sim

# The board's package (docs/deploy.md): dist/visland-*.whl with the companion's hardware config
# template and the shipped model in it; install it with '<wheel>[companion]'.
wheel: $(STAMP)
	rm -rf dist build
	$(BIN)/python -m pip wheel --no-deps --no-build-isolation -q -w dist .

clean:
	rm -rf $(VENV) build dist *.egg-info
