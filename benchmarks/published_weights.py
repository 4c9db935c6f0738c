"""The published weights under illusions: every official checkpoint in a folder, evaluated on its dataset's clean
test split (beside the accuracy its repository reports) and on the simulated illusion suite, then the paper's main
table of those runs beside the paper's numbers.

Usage (a GPU machine with the datasets and the downloaded files):

    python benchmarks/published_weights.py --weights /weights --tusimple /data/tusimple --culane /data/culane \
        --llamas /data/llamas --laneatt-data /src/LaneATT/data --out /runs/published

Each file in --weights (``*.pth``, ``*.pt``, searched recursively) is recognised from its keys and shapes (as
``task=evaluate`` does it); the dataset of a file whose shapes cannot tell it (LaneATT, BezierLaneNet, GANet, a
CLRNet file without its segmentation decoder) from its path (``laneatt_r18_tusimple/models/model_0100.pt``,
``resnet34_bezierlanenet_culane-aug2/model.pt``, ``ganet_culane_resnet18.pth``). Then, per file, two runs of the
project's own commands:

    python -m lanevil_train task=evaluate experiment=official_<family>_<dataset> backbone=<backbone>
        ckpt_path=<file> data.root=<root> task.predictions=true task.out_dir=<out>/<label>/clean
    ... the same with task.suite=synthetic task.out_dir=<out>/<label>/suite

(``--dry-run`` prints them), ``task=report`` over the suites and benchmarks/paper_main_table.py on that report.
A run already finished is skipped (evaluation resumes from its per_image.jsonl). The acceptance check is the clean
column: each file's score on its own test split must equal the "published" one within 0.1 point. LLAMAS is scored
on its valid split (its test labels are not public): CLRNet publishes valid figures; LaneATT's README gives its
test server's, so its LLAMAS rows have no published column.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from lanevil_train.checkpoints import load_checkpoint_file
from lanevil_train.models.official import official_state_dict, recognise

# What each repository's README reports for its files: (family, dataset, backbone) -> (score, value)
PUBLISHED = {
    ("ufld", "tusimple", "resnet18"): ("Accuracy", 95.82),  # cfzd/Ultra-Fast-Lane-Detection README, "This repo"
    ("ufld", "culane", "resnet18"): ("CULane_F1", 69.7),
    ("laneatt", "tusimple", "resnet18"): ("Accuracy", 95.57),  # lucastabelini/LaneATT README
    ("laneatt", "tusimple", "resnet34"): ("Accuracy", 95.63),
    ("laneatt", "culane", "resnet18"): ("CULane_F1", 75.13),
    ("laneatt", "culane", "resnet34"): ("CULane_F1", 76.68),
    ("scnn", "tusimple", "vgg16_bn"): ("Accuracy", 95.17),  # pytorch-auto-drive docs/MODEL_ZOO.md, "best" (the file)
    ("scnn", "culane", "vgg16_bn"): ("CULane_F1", 74.29),
    ("clrnet", "tusimple", "resnet18"): ("Accuracy", 96.84),  # Turoad/CLRNet README, "TuSimple" Acc
    ("clrnet", "tusimple", "resnet34"): ("Accuracy", 96.87),
    ("clrnet", "tusimple", "resnet101"): ("Accuracy", 96.83),
    ("clrnet", "culane", "resnet18"): ("CULane_F1", 79.58),  # README, "CULane" F1@50
    ("clrnet", "culane", "resnet34"): ("CULane_F1", 79.73),
    ("clrnet", "culane", "resnet101"): ("CULane_F1", 80.13),
    ("clrnet", "culane", "dla34"): ("CULane_F1", 80.47),
    # pytorch-auto-drive docs/MODEL_ZOO.md l. 133-134, 174-175: "best" (the file)
    ("bezierlanenet", "tusimple", "resnet18"): ("Accuracy", 95.41),
    ("bezierlanenet", "tusimple", "resnet34"): ("Accuracy", 95.65),
    ("bezierlanenet", "culane", "resnet18"): ("CULane_F1", 73.67),
    ("bezierlanenet", "culane", "resnet34"): ("CULane_F1", 75.57),
    # Wolfwjs/GANet README "Evaluation" (its TuSimple F1 from the mean FP and FN rates, as ours)
    ("ganet", "tusimple", "resnet18"): ("F1", 97.71),
    ("ganet", "tusimple", "resnet34"): ("F1", 97.68),
    ("ganet", "tusimple", "resnet101"): ("F1", 97.45),
    ("ganet", "culane", "resnet18"): ("CULane_F1", 78.79),
    ("ganet", "culane", "resnet34"): ("CULane_F1", 79.39),
    ("ganet", "culane", "resnet101"): ("CULane_F1", 79.63),
    # Turoad/CLRNet README "LLAMAS", valid F1@50 (the split scored here; LaneATT's README LLAMAS figures are its
    # test server's, lib/datasets/llamas.py l. 11: no labels to compare with here)
    ("clrnet", "llamas", "resnet18"): ("CULane_F1", 96.93),
    ("clrnet", "llamas", "dla34"): ("CULane_F1", 97.06),
}
DATASETS = ("tusimple", "culane", "llamas")
CONF = Path(__file__).resolve().parents[1] / "lanevil_train" / "conf" / "experiment"


def describe_file(path: Path) -> dict | None:
    """{family, dataset, backbone, config} of an official file; {"skip": why} for an official file this benchmark
    does not score (a network this project cannot compute, a setting of no published release or dataset here); None
    if it is not an official file this project reads."""
    state = official_state_dict(load_checkpoint_file(path, "--weights"))
    found = recognise(state) if state is not None else None
    if found is None:
        return None
    release, recognised = found
    if recognised.unsupported:
        return {"skip": f"an official {release.name} file ({recognised.what}) that this project cannot load: "
                        f"{recognised.unsupported}"}
    words = dict(item.split("=", 1) for item in recognised.config.split() if "=" in item)
    experiment = words.get("experiment", "")
    if not experiment or any(key.startswith("data.") for key in words) or \
            recognised.what.startswith("an unpublished setting"):
        return {"skip": f"an official {release.name} file ({recognised.what}) of no dataset this benchmark scores "
                        f"(its settings: {recognised.config})"}
    if "unpublished setting" in recognised.what:  # its config needs settings beyond the release's experiment
        return {"skip": f"an official {release.name} file ({recognised.what}) of no published release (its "
                        f"settings: {recognised.config})"}
    dataset = experiment.rsplit("_", 1)[-1]
    named = next((d for d in DATASETS if d in str(path).lower()), None)  # the repositories name it in the path
    if dataset not in DATASETS or named == "llamas":  # LaneATT, GANet: one layout for all; CLRNet: LLAMAS = CULane's
        dataset = named
        if dataset is None:
            raise SystemExit(f"{path}: an official {release.name} file; name its dataset in its path (tusimple, "
                             f"culane or llamas), as the repository's experiment folders and file names do")
    experiment = experiment.replace("<tusimple|culane>", dataset)
    if dataset == "llamas":
        experiment = experiment.rsplit("_", 1)[0] + "_llamas"
        if not (CONF / f"{experiment}.yaml").is_file():
            return {"skip": f"an official {release.name} file of LLAMAS (its path says so), a release this project "
                            f"has no experiment= for"}
    return {"family": release.family, "dataset": dataset, "backbone": words.get("backbone", "resnet18"),
            "experiment": experiment}


def commands(path: Path, info: dict, roots: dict, laneatt_data: Path | None, out: Path) -> dict[str, list[str]]:
    """The clean and suite evaluations of one file."""
    label = f"{info['family']}-{info['backbone']}-{info['dataset']}"
    base = [sys.executable, "-m", "lanevil_train", "task=evaluate", f"experiment={info['experiment']}",
            f"backbone={info['backbone']}", f"ckpt_path={path}", f"data.root={roots[info['dataset']]}",
            f"task.label={label}", "progress=plain"]
    if info["family"] == "laneatt":
        if laneatt_data is None:
            raise SystemExit(f"{path}: a LaneATT file needs --laneatt-data (the repository's data/ folder, with the "
                             f"anchor frequency files)")
        base.append(f"model.head.anchor_frequency_file={laneatt_data / (info['dataset'] + '_anchors_freq.pt')}")
    if (info["family"], info["dataset"], info["backbone"]) == ("clrnet", "llamas", "dla34"):
        base.append("model.decode.nms_threshold=50.0")  # configs/clrnet/clr_dla34_llamas.py (ResNet-18's: 60)
    return {"clean": [*base, "task.predictions=true", f"hydra.run.dir={out / label / 'clean'}"],
            "suite": [*base, "task.suite=synthetic", f"hydra.run.dir={out / label / 'suite'}"]}


def clean_score(run: Path, score: str) -> float:
    row = json.loads((run / "test_scores.json").read_text())[0]
    return float(row[score])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--weights", type=Path, required=True, help="folder of downloaded official checkpoints")
    parser.add_argument("--tusimple", type=Path, help="TuSimple root (test_label.json, clips/)")
    parser.add_argument("--culane", type=Path, help="CULane root (list/test.txt, the driver_* folders)")
    parser.add_argument("--llamas", type=Path, help="LLAMAS root (color_images/, labels/; scored on valid)")
    parser.add_argument("--laneatt-data", type=Path, help="LaneATT's data/ folder (its *_anchors_freq.pt files)")
    parser.add_argument("--out", type=Path, default=Path("published_runs"))
    parser.add_argument("--dry-run", action="store_true", help="print the commands, run nothing")
    args = parser.parse_args(argv)

    roots = {"tusimple": args.tusimple, "culane": args.culane, "llamas": args.llamas}
    files = sorted(p for p in args.weights.rglob("*") if p.suffix in (".pth", ".pt") and p.is_file())
    plan = []
    for path in files:
        info = describe_file(path)
        if info is None:
            print(f"skipped {path}: not an official checkpoint this project reads")
            continue
        if "skip" in info:
            print(f"skipped {path}: {info['skip']}")
            continue
        if roots[info["dataset"]] is None:
            print(f"skipped {path}: a {info['dataset']} file and no --{info['dataset']} root")
            continue
        plan.append((path, info, commands(path, info, roots, args.laneatt_data, args.out)))
    if not plan:
        raise SystemExit(f"{args.weights}: no official checkpoint to evaluate")

    for path, info, runs in plan:
        for kind, cmd in runs.items():
            if args.dry_run:
                print(" ".join(map(str, cmd)))
                continue
            run_dir = Path(cmd[-1].split("=", 1)[1])
            if (run_dir / "test_scores.json").is_file() and kind == "clean":
                continue
            subprocess.run(cmd, check=True)
    if args.dry_run:
        return 0

    print("\n| file | dataset | score | ours | published | difference |\n|---|---|---|---|---|---|")
    for path, info, runs in plan:
        score, published = PUBLISHED.get((info["family"], info["dataset"], info["backbone"]), ("Accuracy", None))
        ours = clean_score(Path(runs["clean"][-1].split("=", 1)[1]), score)
        difference = "" if published is None else f"{ours - published:+.2f}"
        print(f"| {path.name} | {info['dataset']} | {score} | {ours:.2f} | {published or '-'} | {difference} |")

    suites = [str(Path(runs["suite"][-1].split("=", 1)[1])) for _, _, runs in plan]
    report = args.out / "report"
    subprocess.run([sys.executable, "-m", "lanevil_train", "task=report", f"task.runs=[{','.join(suites)}]",
                    f"hydra.run.dir={report}"], check=True)
    subprocess.run([sys.executable, str(Path(__file__).with_name("paper_main_table.py")), str(report)], check=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
