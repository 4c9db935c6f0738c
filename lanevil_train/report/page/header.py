"""The header every report.html has: the model(s), each one's weights sha256 (the hash of the network's state dict
that streaming wrote to <results>.run.json beside its per_image.jsonl) and checkpoint (ckpt_path of the run's config,
when the run read one), the command line (Hydra's .hydra/overrides.yaml in the run folder or the one above it, else
sys.argv), the package version and the date the page was written.
"""

from __future__ import annotations

import datetime
import json
import shlex
import sys
from pathlib import Path
from typing import Sequence

from lanevil_train.report.page.html import Page, esc


# ------------------------------------------------------------------------------------------------------ header
def command_line(out_dir: str | Path) -> str:
    """The command that made the run: Hydra's .hydra/overrides.yaml in out_dir or its parent (a training run's
    robustness/), else this process's sys.argv."""
    out_dir = Path(out_dir)
    for folder in (out_dir, out_dir.parent):
        overrides = folder / ".hydra" / "overrides.yaml"
        if overrides.is_file():
            from omegaconf import OmegaConf

            try:
                values = OmegaConf.to_container(OmegaConf.load(overrides))
            except Exception:  # noqa: BLE001 -- a header line is not worth failing a run for
                continue
            if isinstance(values, list):
                return "python -m lanevil_train " + " ".join(shlex.quote(str(v)) for v in values)
    argv = list(sys.argv)
    if argv and argv[0].replace("\\", "/").endswith("lanevil_train/__main__.py"):
        return "python -m lanevil_train " + " ".join(shlex.quote(a) for a in argv[1:])
    return " ".join(shlex.quote(a) for a in argv)


def _run_config_value(results: Path, key: str):
    """`key` of the config nearest above a results file (.hydra/config.yaml or a compare run's config.yaml)."""
    from omegaconf import OmegaConf

    for folder in (results.parent, results.parent.parent):
        for config in (folder / ".hydra" / "config.yaml", folder / "config.yaml"):
            if config.is_file():
                try:
                    return OmegaConf.select(OmegaConf.load(config), key)
                except Exception:  # noqa: BLE001
                    return None
    return None


def run_identities(result_files: Sequence[Path], labels: dict[Path, str] | None = None) -> list[dict]:
    """Per results file: its model label, the weights hash its <stem>.run.json holds, the run's ckpt_path."""
    labels = labels or {}
    out = []
    for path in map(Path, result_files):
        marker = path.with_name(f"{path.stem}.run.json")
        identity = {}
        if marker.is_file():
            try:
                identity = json.loads(marker.read_text(encoding="utf-8"))
            except ValueError:
                identity = {}
        model = labels.get(path) or identity.get("model")
        if model is None:
            try:
                with open(path, encoding="utf-8") as handle:
                    model = json.loads(handle.readline()).get("model")
            except (OSError, ValueError):
                model = None
        out.append({"model": model, "dataset": identity.get("dataset"),
                    "weights_sha256": identity.get("weights_sha256"),
                    "checkpoint": _run_config_value(path, "ckpt_path") or identity.get("vlm.path"),
                    "results": str(path)})
    return out


def add_run_header(page: Page, out_dir: Path, identities: Sequence[dict] = (), models: Sequence[str] = ()) -> None:
    """The header lines every page has: models (with weights hash and checkpoint where known), command, version,
    date."""
    from lanevil_train import __version__

    lines = []
    seen = set()
    for ident in identities:
        if ident.get("model") is None or (ident["model"], ident.get("dataset")) in seen:
            continue
        seen.add((ident["model"], ident.get("dataset")))
        bits = [f"<b>{esc(ident['model'])}</b>"]
        if ident.get("dataset"):
            bits.append(f"on {esc(ident['dataset'])}")
        if ident.get("weights_sha256"):
            bits.append(f"weights sha256 <code>{esc(ident['weights_sha256'])}</code>")
        if ident.get("checkpoint"):
            bits.append(f"checkpoint <code>{esc(ident['checkpoint'])}</code>")
        lines.append(" · ".join(bits))
    known = {ident.get("model") for ident in identities}
    lines += [f"<b>{esc(m)}</b>" for m in models if m not in known]
    if lines:
        page.add_header("models", "<br>".join(lines))
    page.add_header("command", f"<code>{esc(command_line(out_dir))}</code>")
    page.add_header("lanevil_train", esc(__version__))
    page.add_header("written", esc(datetime.datetime.now().astimezone().isoformat(timespec="seconds")))
