"""The learned policy's networks (torch): the perception CNN and the LSTM controller."""

from __future__ import annotations

import math

import torch
from torch import nn

from companion.policy_net.config import NetConfig
from companion.policy_net.geometry import HOVER_FEATURE_SCALE, feature_names

__all__ = ["ControlLSTM", "PerceptionCNN"]


class PerceptionCNN(nn.Module):
    """Image -> (tan_right, tan_forward, visibility logit) of the pad centre.

    Four strided/dilated 3x3 convolutions to a 16x16 heat map, soft-argmax over the map gives the
    expected pixel of the pad centre (sub-cell precision, translation-equivariant), converted to a
    bearing with the pinhole model; visibility from the pooled features and the map's peak.
    """

    def __init__(self, cfg: NetConfig) -> None:
        super().__init__()
        c1, c2, c3, c4 = cfg.cnn_channels
        self.features = nn.Sequential(
            nn.Conv2d(1, c1, 5, stride=2, padding=2),
            nn.ReLU(inplace=True),
            nn.Conv2d(c1, c2, 3, stride=2, padding=1),
            nn.ReLU(inplace=True),
            nn.Conv2d(c2, c3, 3, stride=2, padding=1),
            nn.ReLU(inplace=True),
            nn.Conv2d(c3, c4, 3, stride=1, padding=2, dilation=2),
            nn.ReLU(inplace=True),
            *(
                m
                for _ in range(cfg.cnn_context_layers)
                for m in (nn.Conv2d(c4, c4, 3, stride=1, padding=4, dilation=4), nn.ReLU(True))
            ),
        )
        self.heat = nn.Conv2d(c4, 1, 1)
        self.visibility = nn.Linear(c4 + 1, 1)
        self.bias = nn.Parameter(torch.zeros(2))
        size = cfg.image_size_px
        cells = size // 8
        focal = 0.5 * size / math.tan(math.radians(cfg.fov_deg) / 2)
        centres = (torch.arange(cells, dtype=torch.float32) + 0.5) * (size / cells)
        self.register_buffer("tan_cols", (centres - size / 2) / focal, persistent=False)
        self.register_buffer("tan_rows", (size / 2 - centres) / focal, persistent=False)

    def forward(self, image_u8: torch.Tensor) -> torch.Tensor:
        """``image_u8``: (B, H, W) or (B, 1, H, W), uint8 or float in [0, 255]. Returns (B, 3)."""
        x = image_u8
        if x.dim() == 3:
            x = x.unsqueeze(1)
        x = x.float() * (1.0 / 255.0) - 0.5
        f = self.features(x)
        logits = self.heat(f).flatten(1)  # (B, cells*cells)
        prob = torch.softmax(logits, dim=1)
        cells = self.tan_cols.numel()
        prob = prob.view(-1, cells, cells)
        tan_right = (prob.sum(dim=1) * self.tan_cols).sum(dim=1)
        tan_forward = (prob.sum(dim=2) * self.tan_rows).sum(dim=1)
        pooled = f.mean(dim=(2, 3))
        peak = logits.max(dim=1, keepdim=True).values
        vis = self.visibility(torch.cat([pooled, peak], dim=1)).squeeze(1)
        return torch.stack([tan_right + self.bias[0], tan_forward + self.bias[1], vis], dim=1)


class ControlLSTM(nn.Module):
    """Features -> Command with explicit LSTM state; outputs always inside the Command ranges.

    ``thrust_norm = sigmoid(z0 + logit(hover))`` (zero output = hover) and
    ``rates = max_rate * tanh(z)``. ``hover`` is the config's, or with ``hover_input`` the
    autopilot's hover thrust given as the last input feature (so one model centres its thrust
    on the vehicle it flies).
    """

    def __init__(self, cfg: NetConfig) -> None:
        super().__init__()
        n_in = len(feature_names(cfg.hover_input))
        self.hover_input = cfg.hover_input
        self.encoder = nn.Sequential(nn.Linear(n_in, cfg.mlp_hidden), nn.Tanh())
        self.lstm = nn.LSTM(cfg.mlp_hidden, cfg.lstm_hidden, batch_first=True)
        self.head = nn.Sequential(
            nn.Linear(cfg.lstm_hidden + cfg.mlp_hidden, cfg.mlp_hidden),
            nn.Tanh(),
            nn.Linear(cfg.mlp_hidden, 4),
        )
        self.hidden = cfg.lstm_hidden
        self.register_buffer(
            "hover_logit",
            torch.tensor(math.log(cfg.hover_thrust_norm / (1 - cfg.hover_thrust_norm))),
            persistent=False,
        )
        self.register_buffer(
            "max_rate", torch.tensor(cfg.max_rate_rad_s, dtype=torch.float32), persistent=False
        )

    def zero_state(self, batch: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
        z = torch.zeros(1, batch, self.hidden)
        return z, z.clone()

    def forward(
        self, features: torch.Tensor, state: tuple[torch.Tensor, torch.Tensor] | None = None
    ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """``features`` (B, T, F) -> commands (B, T, 4) = (thrust_norm, p, q, r), next state."""
        e = self.encoder(features)
        if state is None:
            state = self.zero_state(features.shape[0])
        h, state = self.lstm(e, state)
        z = self.head(torch.cat([h, e], dim=-1))
        if self.hover_input:
            hover = (features[..., -1:] * HOVER_FEATURE_SCALE).clamp(0.02, 0.98)
            hover_logit = torch.log(hover / (1.0 - hover))
        else:
            hover_logit = self.hover_logit
        thrust = torch.sigmoid(z[..., :1] + hover_logit)
        rates = self.max_rate * torch.tanh(z[..., 1:])
        return torch.cat([thrust, rates], dim=-1), state
