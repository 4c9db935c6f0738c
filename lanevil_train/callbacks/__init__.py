"""Model-aware defenses as Lightning callbacks that work on any LightningModule (torch and Lightning only).

    from lanevil_train.callbacks import AttentionAreaMixing
    trainer = pl.Trainer(callbacks=[AttentionAreaMixing(layer="backbone.layer4")])
"""

from lanevil_train.callbacks.aam import AttentionAreaMixing, RegionBank
from lanevil_train.callbacks.adapter import BatchAdapter
from lanevil_train.callbacks.pgd import PGDAdversarialTraining

__all__ = ["AttentionAreaMixing", "BatchAdapter", "PGDAdversarialTraining", "RegionBank"]
