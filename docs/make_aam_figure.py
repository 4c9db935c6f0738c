"""Draw what AAM++ does on one training batch: attention maps of the hard examples with their mismatched
high- (red) and low-attention (blue) regions, and the batch images after mixing (changed areas outlined).

Usage: python docs/make_aam_figure.py --ckpt outputs/train/<date>/checkpoints/last.ckpt [--out docs/aam.png]
The checkpoint is a trained `experiment=quickstart` LaneATT (an untrained model has no meaningful attention).
"""

from __future__ import annotations

import argparse

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from aam_step import observed_step  # noqa: E402  (docs/, beside this script)
from hydra import compose, initialize_config_module  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402

from lanevil_train.callbacks.regions import HAA, LAA, extract_regions  # noqa: E402
from lanevil_train.data.normalization import unnormalize_image  # noqa: E402
from lanevil_train.tasks.builders import build_datamodule, build_defense, build_model, model_config  # noqa: E402

COLOURS = {HAA: "red", LAA: "deepskyblue"}


def to_rgb(image: torch.Tensor, normalize: str = "imagenet") -> np.ndarray:
    """A network input back as an RGB image in [0, 1] (the quickstart's model trains on `imagenet` inputs)."""
    return np.clip(unnormalize_image(image.numpy(), normalize), 0, 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--ckpt", required=True)
    parser.add_argument("--out", default="docs/aam.png")
    parser.add_argument("--seed", type=int, default=3)
    args = parser.parse_args()
    with initialize_config_module(config_module="lanevil_train.conf", version_base="1.3"):
        cfg = compose(config_name="config", overrides=["experiment=quickstart", "defense=aam++",
                                                       "data.train.num_scenes=64", "output_dir=/tmp/aam_figure",
                                                       f"seed={args.seed}"])
    torch.manual_seed(args.seed)
    model = build_model(model_config(cfg))
    model.load_state_dict(torch.load(args.ckpt, map_location="cpu", weights_only=False)["state_dict"])
    aam = build_defense(cfg)["callback"]
    aam.mix_prob = 1.0
    batches = iter(build_datamodule(cfg, ("train",), model).train_dataloader())
    batch = next(batches)

    scores, harder, hard, cams = observed_step(aam, model, batch, batch["images"])
    masks = aam.adapter_masks(batch)
    hard_idx = [i for i in range(len(scores)) if (scores[i] > scores.mean() if harder else scores[i] < scores.mean())]

    target = next(batches)
    before = target["images"].clone()
    aam.mix(target["images"], aam.adapter_masks(target))
    aam.on_fit_end(None, model)

    rows = max(len(hard_idx), 1)
    fig, axes = plt.subplots(rows, 3, figsize=(12, 1.6 * rows + 0.6), squeeze=False)
    for row in range(rows):
        for ax in axes[row]:
            ax.axis("off")
    for row, i in enumerate(hard_idx[:rows]):
        regions = extract_regions(cams[i], masks[i], aam.kinds, aam.sigma, aam.t_haa, aam.t_laa, aam.min_area,
                                  aam.overlap_threshold)
        axes[row, 0].imshow(to_rgb(batch["images"][i]))
        axes[row, 0].imshow(np.ma.masked_where(~masks[i], masks[i]), cmap="autumn", alpha=0.6)
        axes[row, 0].set_title(f"hard example (train accuracy {scores[i]:.2f}) + lane mask", fontsize=8)
        axes[row, 1].imshow(to_rgb(batch["images"][i]))
        axes[row, 1].imshow(cams[i], cmap="jet", alpha=0.45)
        for kind, boxes in regions.items():
            for box in boxes:
                axes[row, 1].add_patch(Rectangle((box.x0, box.y0), box.width, box.height, fill=False,
                                                 edgecolor=COLOURS[kind], linewidth=1.5))
        axes[row, 1].set_title("attention (Grad-CAM) and mismatched HAA (red) / LAA (blue)", fontsize=8)
        changed = (target["images"][row] != before[row]).any(dim=0).numpy()
        axes[row, 2].imshow(to_rgb(target["images"][row]))
        if changed.any():
            ys, xs = np.nonzero(changed)
            axes[row, 2].add_patch(Rectangle((xs.min(), ys.min()), xs.max() - xs.min() + 1, ys.max() - ys.min() + 1,
                                             fill=False, edgecolor="yellow", linewidth=1.5))
        axes[row, 2].set_title("a training image after mixing (yellow: the blended region)", fontsize=8)
    fig.suptitle(f"AAM++ on one quickstart batch: {len(hard)} regions banked from {len(hard_idx)} hard examples",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
