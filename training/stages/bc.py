"""Stage ``bc`` (paper 4.3, stage 1): the privileged LSTM cloned from the expert's flights,
``checkpoints/bc.pt``."""

from __future__ import annotations

import torch

from companion.policy_net import ControlLSTM, save_checkpoint
from training.run_folder import Run
from training.stage_records import BcRecord
from training.stages.fitting import fit_controller, privileged_buffer

__all__ = ["run"]


def run(r: Run) -> BcRecord:
    p = r.profile
    torch.manual_seed(p.seed)
    cfg = r.net_config("privileged")
    control = ControlLSTM(cfg)
    buf, names = privileged_buffer(r, 0, cfg)
    fit = fit_controller(r, control, buf, p.bc_steps, p.lr, "bc", p.seed)
    path = save_checkpoint(
        r.root / "checkpoints" / "bc.pt",
        cfg,
        control,
        None,
        r.metadata("bc", {"episodes": names, "fit": fit.to_dict()}),
    )
    return r.finish(BcRecord(stage="bc", git_commit=r.commit, checkpoint=str(path), fit=fit))
