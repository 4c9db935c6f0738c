"""Draw what AAM++ does to a VLM's frames in one fine-tuning step: for the hardest clips of a batch, each frame's
attention (Grad-CAM at the family's vision output, laid on the frame by vlm/training/vision_maps.py) with its mismatched
high- (red) and low-attention (blue) regions, and frames of the next batch after mixing (the blended areas
outlined).

Usage: python docs/make_vlm_aam_figure.py --model outputs/train/<date>/model [--out docs/vlm_aam.png]
The model is a trained VLM saved in the Hugging Face format, e.g. the `experiment=vlm_quickstart` run's model/ (an
untrained model's attention means nothing); the clips are rendered at --size, the frame size it was trained at.
"""

from __future__ import annotations

import argparse

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from aam_step import observed_step  # noqa: E402  (docs/, beside this script)
from matplotlib.patches import Rectangle  # noqa: E402
from torch.utils.data import DataLoader  # noqa: E402

from lanevil_train.callbacks import AttentionAreaMixing, BatchAdapter  # noqa: E402
from lanevil_train.callbacks.regions import HAA, LAA, extract_regions  # noqa: E402
from lanevil_train.vlm.clips.clip_set import SyntheticClipSuite  # noqa: E402
from lanevil_train.vlm.clips.qa_data import ClipQADataset, collate_clip_qa  # noqa: E402
from lanevil_train.vlm.training.finetune import VLMFineTuner  # noqa: E402

COLOURS = {HAA: "red", LAA: "deepskyblue"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", required=True, help="a trained VLM's folder (save_pretrained)")
    parser.add_argument("--out", default="docs/vlm_aam.png")
    parser.add_argument("--size", type=int, nargs=2, default=(64, 112), metavar=("H", "W"))
    parser.add_argument("--seed", type=int, default=2)
    parser.add_argument("--clips", type=int, default=2, help="hard clips drawn")
    args = parser.parse_args()
    torch.manual_seed(args.seed)
    module = VLMFineTuner(args.model, lora=None, frames_as="video")
    aam = AttentionAreaMixing(layer=module.attention_layer(), mode="aam++", feature_map=module.vision_maps,
                              mix_prob=1.0, adapter=BatchAdapter(images="images", lanes="lanes"), seed=args.seed)
    suite = SyntheticClipSuite(4, 1_000_000 + 50 * args.seed, illusions=["fence_shadow", "road_repair", "vehicle",
                                                                          "sunlight_reflection"],
                               severities=(5,), size=tuple(args.size), per_clip=5)
    data = ClipQADataset(suite, "all")
    loader = iter(DataLoader(data, batch_size=8, shuffle=True, collate_fn=collate_clip_qa,
                             generator=torch.Generator().manual_seed(args.seed)))
    batch = module.on_after_batch_transfer(next(loader), 0)

    images = batch["images"]
    scores, _, found, cams = observed_step(aam, module, batch, images)
    masks = aam.adapter_masks(batch)
    clip_loss = scores[::6]
    hard_clips = [int(c) for c in np.argsort(-clip_loss) if clip_loss[c] > clip_loss.mean()][:args.clips]

    target = module.on_after_batch_transfer(next(loader), 0)
    before = target["images"].clone()
    aam.mix(target["images"], aam.adapter_masks(target))
    aam.on_fit_end(None, module)

    frames = (0, 2, 5)
    fig, axes = plt.subplots(len(hard_clips) + 1, len(frames) * 2, figsize=(2.2 * 2 * len(frames),
                                                                            1.5 * (len(hard_clips) + 1) + 0.6),
                             squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for row, clip in enumerate(hard_clips):
        for col, k in enumerate(frames):
            i = clip * 6 + k
            rgb = images[i].permute(1, 2, 0).numpy()
            regions = extract_regions(cams[i], masks[i], aam.kinds, aam.sigma, aam.t_haa, aam.t_laa, aam.min_area,
                                      aam.overlap_threshold)
            axes[row, 2 * col].imshow(rgb)
            axes[row, 2 * col].imshow(np.ma.masked_where(~masks[i], masks[i]), cmap="autumn", alpha=0.6)
            axes[row, 2 * col].set_title(f"clip {clip} frame {k}: lanes", fontsize=7)
            axes[row, 2 * col + 1].imshow(rgb)
            axes[row, 2 * col + 1].imshow(cams[i], cmap="jet", alpha=0.45)
            for kind, boxes in regions.items():
                for box in boxes:
                    axes[row, 2 * col + 1].add_patch(Rectangle((box.x0, box.y0), box.width, box.height, fill=False,
                                                               edgecolor=COLOURS[kind], linewidth=1.2))
            axes[row, 2 * col + 1].set_title(f"attention; loss {clip_loss[clip]:.2f}", fontsize=7)
    changed = [i for i in range(len(before)) if not torch.equal(target["images"][i], before[i])][:len(frames) * 2]
    for col, i in enumerate(changed):
        ax = axes[-1, col]
        ax.imshow(target["images"][i].permute(1, 2, 0).numpy())
        diff = (target["images"][i] != before[i]).any(dim=0).numpy()
        ys, xs = np.nonzero(diff)
        ax.add_patch(Rectangle((xs.min(), ys.min()), xs.max() - xs.min() + 1, ys.max() - ys.min() + 1, fill=False,
                               edgecolor="yellow", linewidth=1.2))
        ax.set_title(f"next batch, frame {i % 6}: mixed", fontsize=7)
    fig.suptitle(f"AAM++ on a VLM's frames: {len(found)} regions banked from the hard clips' frames "
                 f"(red HAA, blue LAA), then blended into the next batch", fontsize=9)
    fig.tight_layout()
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
