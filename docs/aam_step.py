"""One training step by hand for the AAM figures (make_aam_figure.py, make_vlm_aam_figure.py): the callback's hooks
keep the attention layer's activation and the gradient of its backward, the hard examples' regions go to its bank,
and the Grad-CAM maps are returned at the images' size."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from lanevil_train.callbacks.regions import grad_cam


def observed_step(aam, module, batch: dict, images: torch.Tensor) -> tuple[torch.Tensor, bool, list, np.ndarray]:
    """-> (per-sample scores, whether higher is harder, the banked (kind, patch) regions, Grad-CAM per image)."""
    aam.on_fit_start(None, module)
    module.train()
    aam._capture = True
    out = module.training_step(batch, 0)
    out["loss"].backward()
    aam._capture = False
    scores, harder = aam.per_sample_scores(out)
    found = aam.harvest(aam._activation, aam._gradient, scores, harder, batch)
    for kind, patch in found:
        aam.bank.add(kind, patch)
    cams = grad_cam(aam._activation, aam._gradient)
    cams = F.interpolate(cams[:, None], size=images.shape[-2:], mode="bilinear")[:, 0].numpy()
    return scores, harder, found, cams
