"""The clip suite: written to disk by `task=build data=clips`, read back as a dataset, or generated on the fly.

On disk (root/): clips/<case>/<segment>/<variant>/<k>.png (6 frames per clip variant, variant `clean` or `s<N>`;
`<name>-s<N>` in a corruption or combined suite), `clips.jsonl` (one line per clip variant), `qa.jsonl` (one line
per QA of a base clip) and `build.json` (the plan, the counts, and whether the set is complete).

Suite kinds (perturbations.SUITE_KINDS, recorded in the plan; a set without one is an illusion suite): each base
clip's clean clip, then each severity of its case's illusion (illusions), of every corruption (corruptions), or of
the case's illusion, its second illusion and the pair "a+b" (combined; vlm/clips/clips.py). All variants of a base clip
come from one render of the scene. A corruption suite's QA leaves out the questions whose template reads a fact in
vlm/clips/suite_qa.py's CORRUPTION_UNSAFE_FACTS (the illusion, which is not drawn; the weather and light, which weather
and brightness corruptions change the look of), and base clips left without a question.

Safe to kill at any instant, like the image builder (data/illusion_set.py): frames are written atomically, then
the base clip's QA lines, then its variants' clip lines, each durable before the next, so a clip line promises
its frames and QA; both JSON-lines files are ResultsLogs (a torn last line is cut on rerun, finished keys are
skipped); temporaries a kill left are removed first; build.json says "complete": false until the last clip.

Item form shared by ClipSetDataset and SyntheticClipSuite: {"frames": 6 uint8 RGB arrays, "qa": the QA of the
item's base clip, "meta": {clip_id, base_clip_id, case_id, segment, illusion, category, severity, seed}};
`clip_meta(i)` and `qa_for(base_clip_id)` give the same without loading or rendering frames.
"""

from __future__ import annotations

import difflib
import hashlib
import json
from collections import OrderedDict
from pathlib import Path
from typing import Callable, Iterator, Sequence

import cv2
import numpy as np
from torch.utils.data import Dataset

from lanevil_train.data.formats import builds, load_image
from lanevil_train.data.formats.builds import BUILD_FILE, map_jobs, write_build_record
from lanevil_train.files.atomic import atomic_write_bytes
from lanevil_train.illusions.registry import check_severity, get_illusion
from lanevil_train.perturbations import PAIR, check_kind, get_perturbation, suite_names
from lanevil_train.progress import progress_counter
from lanevil_train.results_log import ResultsLog
from lanevil_train.taxonomy import ILLUSION_CATEGORY, ILLUSION_NAMES
from lanevil_train.vlm.clips.qa import scene_classes, training_aids
from lanevil_train.vlm.clips.qa_records import check_qa_record
from lanevil_train.vlm.clips.suite_qa import QA_PLAN, kept_questions, suite_qa

CLIPS_FILE = "clips.jsonl"
QA_FILE = "qa.jsonl"
SEGMENTS = ("before", "over", "alongside")
META_KEYS = ("clip_id", "base_clip_id", "case_id", "segment", "illusion", "category", "severity", "seed")
Paraphraser = Callable[[list], list]


def _geometry():
    """The clip renderer (vlm/clips/clips.py), imported when first needed; tests may replace this function."""
    from lanevil_train.vlm.clips import clips

    return clips


# ---------------------------------------------------------------------------------------------- naming

def base_clip_id(case, segment: str) -> str:
    return f"{case.case_id}-{segment}"


def clip_variant_names(case, kind: str = "illusions", names: Sequence[str] = ()) -> tuple[str, ...]:
    """The perturbations a base clip of `case` gets in a `kind` suite, each at every severity: the case's illusion
    (illusions), each of `names` (corruptions), or the case's illusion, its second and the pair (combined)."""
    if check_kind(kind) == "illusions":
        return (case.illusion,)
    if kind == "corruptions":
        return tuple(names)
    second = getattr(case, "second", None)
    if second is None:
        raise ValueError(f"cases: {case.case_id} has no second illusion; a combined suite takes its cases from "
                         f"clips.combined_clip_cases")
    return case.illusion, second, f"{case.illusion}{PAIR}{second}"


def variant_records(case, segment: str, severities: Sequence[int], kind: str = "illusions",
                    names: Sequence[str] = ()) -> list[dict]:
    """The clips.jsonl records of one base clip: the clean clip first, then each severity of each of its
    perturbations (clip_variant_names); variant `s<N>` in an illusion suite, `<name>-s<N>` otherwise."""
    base = base_clip_id(case, segment)
    folder = case.case_id.replace("/", "_").replace(".", "_")
    variants = [(None, 0, "clean")] + [(name, sev, f"s{sev}" if kind == "illusions" else f"{name}-s{sev}")
                                       for name in clip_variant_names(case, kind, names) for sev in severities]
    return [{"clip_id": f"{base}-{variant}", "base_clip_id": base, "case_id": case.case_id, "segment": segment,
             "illusion": name, "category": _category(name) if severity else None, "severity": severity,
             "seed": case.seed, "frames": [f"clips/{folder}/{segment}/{variant}/{k}.png" for k in range(6)]}
            for name, severity, variant in variants]


def _category(name: str) -> str:
    return ILLUSION_CATEGORY[name] if name in ILLUSION_CATEGORY else get_perturbation(name).category


# ---------------------------------------------------------------------------------------------- QA of a suite

def suite_base_clips(cases: Sequence, kind: str = "illusions", per_clip: int = 5) -> list[tuple]:
    """(case, segment) of every base clip of a `kind` suite: all 3 segments of each case, less (corruption suite)
    those none of whose questions is kept."""
    return [(case, segment) for case in cases for segment in SEGMENTS
            if kept_questions(kind, case.seed, segment, per_clip)]


# ---------------------------------------------------------------------------------------------- building

def _write_frame(path: Path, frame: np.ndarray) -> None:
    ok, encoded = cv2.imencode(".png", cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    if not ok:
        raise OSError(f"cv2 could not encode {path}")
    atomic_write_bytes(path, encoded.tobytes())


def truth_of(args: tuple) -> dict:
    """The scene truth of one base clip (case, segment, size): a worker's job."""
    case, segment, size = args
    return _geometry().clip_truth(case, segment, size=tuple(size))


def plan_qa(bases: Sequence[tuple], size: Sequence[int], per_clip: int, kind: str, workers: int = 0,
            progress: str = "auto", truths: dict | None = None) -> dict[str, list[dict]]:
    """{base clip id: its QA} of the base clips `bases` ((case, segment) in suite order), planned together
    (suite_qa.suite_qa) from their truth, computed in `workers` processes; `truths` (base clip id -> truth) holds
    those known already and is given the others."""
    truths = {} if truths is None else truths
    todo = [(case, segment) for case, segment in bases if base_clip_id(case, segment) not in truths]
    bar = progress_counter(len(todo), desc="scene truth for the QA", unit="base clip", mode=progress)
    for (case, segment), truth in zip(todo, map_jobs(truth_of, [(c, s, tuple(size)) for c, s in todo], workers)):
        truths[base_clip_id(case, segment)] = truth
        bar.update(1)
    bar.close()
    return suite_qa([(base_clip_id(c, s), c.seed, truths[base_clip_id(c, s)]) for c, s in bases], per_clip, kind)


def render_with_truth(args: tuple) -> tuple[dict | None, dict]:
    """(every variant's frames, or None when `frames` is false; the truth) of one base clip: a worker's job."""
    case, segment, severities, size, kind, names, frames = args
    renders = _render(case, segment, severities, tuple(size), kind, names) if frames else None
    return renders, _geometry().clip_truth(case, segment, size=tuple(size))


def render_base_clip(args: tuple) -> tuple[dict, list[dict]]:
    """Render one base clip's variants, write the frames of those not yet done; (truth, their records)."""
    case, segment, severities, size, root, done, kind, names = args
    todo = [r for r in variant_records(case, segment, severities, kind, names) if r["clip_id"] not in done]
    clips, truth = render_with_truth((case, segment, severities, size, kind, names, bool(todo)))
    for record in todo:
        frames = clips[(record["illusion"], record["severity"])]
        if len(frames) != 6:
            raise ValueError(f"render_clip({record['clip_id']}): expected 6 frames, got {len(frames)}")
        for path, frame in zip(record["frames"], frames):
            _write_frame(Path(root) / path, frame)
    return truth, todo


def _render(case, segment: str, severities: Sequence[int], size: tuple, kind: str,
            names: Sequence[str]) -> dict[tuple, list[np.ndarray]]:
    """{(illusion name or None, severity): 6 frames} of every variant of a base clip, from one render of the scene."""
    if kind == "illusions":
        clips = _geometry().render_clip(case, segment, [0, *severities], size=size)
        return {(case.illusion if sev else None, sev): frames for sev, frames in clips.items()}
    return _geometry().render_variants(case, segment, clip_variant_names(case, kind, names), [0, *severities],
                                       size=size)


def paraphrase_qa(qas: list[dict], paraphraser: Paraphraser | None) -> list[dict]:
    """The QA with question texts and open answers rewritten by `paraphraser` (list[str] -> list[str])."""
    if paraphraser is None or not qas:
        return qas
    slots = [(i, "question") for i in range(len(qas))] + [(i, "answer") for i, q in enumerate(qas)
                                                          if q["type"] == "open"]
    texts = [qas[i][field] for i, field in slots]
    out = paraphraser(list(texts))
    if not isinstance(out, list) or len(out) != len(texts) or not all(isinstance(t, str) and t for t in out):
        raise ValueError(f"paraphraser: expected a list of {len(texts)} non-empty strings (one per text given), "
                         f"got {type(out).__name__} of {len(out) if hasattr(out, '__len__') else '?'}")
    qas = [dict(q) for q in qas]
    for (i, field), text in zip(slots, out):
        qas[i][field] = text
    return qas


def _cases_digest(cases) -> str:
    plain = [[c.case_id, c.seed, c.illusion, *([c.second] if getattr(c, "second", None) else [])] for c in cases]
    return hashlib.sha256(json.dumps(plain).encode("utf-8")).hexdigest()[:16]


def _check_build_arguments(cases, severities, size, kind: str = "illusions", names: Sequence[str] = ()) -> None:
    if not cases:
        raise ValueError("build_clip_set: cases: expected at least one case, got none")
    for i, case in enumerate(cases):
        get_illusion(case.illusion)  # names the known ones
        drawn = clip_variant_names(case, kind, names)[:2] if kind != "corruptions" else ()
        if names and any(n not in names for n in drawn):
            raise ValueError(f"cases[{i}]: {case.case_id} draws {' and '.join(drawn)}, expected illusions among "
                             f"the suite's names {list(names)}")
    if not severities:
        raise ValueError("severities: expected a non-empty list of integers 1..5, got an empty list")
    for severity in severities:
        check_severity(severity)
    if len(size) != 2 or not all(isinstance(s, int) and s >= 16 for s in size):
        raise ValueError(f"size: expected (height, width), two integers >= 16, got {tuple(size)}")


def build_clip_set(cases: Sequence, severities: Sequence[int], root: str | Path, size: tuple[int, int] = (360, 640),
                   workers: int = 0, progress: str = "auto", paraphraser: Paraphraser | None = None,
                   per_clip: int = 5, kind: str = "illusions", names: str | Sequence[str] = "all") -> dict:
    """Write every case's clips (3 segments x clean + each perturbation x severity of the `kind` suite, `names`
    the corruptions of a corruption suite), QA and records under root, resumably; a summary {root, clips, written,
    skipped, qa}. `paraphraser` rewrites question texts and open answers."""
    root, severities, size, names = Path(root), tuple(severities), tuple(size), suite_names(kind, names)
    _check_build_arguments(cases, severities, size, kind, names)
    bases = suite_base_clips(cases, kind, per_clip)
    plan = {"size": list(size), "severities": list(severities), "per_clip": per_clip,
            "paraphrased": paraphraser is not None, "cases_digest": _cases_digest(cases), "qa_plan": QA_PLAN}
    if kind != "illusions":  # an illusion suite's plan stays as it was: sets built before suite kinds resume
        plan.update(kind=kind, names=list(names))
    expected = {"clips": sum(len(variant_records(c, s, severities, kind, names)) for c, s in bases),
                "base_clips": len(bases), "qa": sum(len(kept_questions(kind, c.seed, s, per_clip)) for c, s in bases),
                "cases": len(cases), "plan": plan}
    builds.begin_build(root, expected, "clips", "clip set", "task=build data=clips")
    clip_log, qa_log = ResultsLog(root / CLIPS_FILE, "clip_id"), ResultsLog(root / QA_FILE, "qa_id")
    done_clips, done_qa = clip_log.resume(), qa_log.resume()
    clip_log.path.touch()
    qa_log.path.touch()
    jobs = [(case, segment, severities, size, str(root), frozenset(done_clips), kind, names)
            for case, segment in bases
            if any(r["clip_id"] not in done_clips for r in variant_records(case, segment, severities, kind, names))]
    planned = plan_qa(bases, size, per_clip, kind, workers, progress) if jobs else {}
    bar = progress_counter(expected["clips"], len(done_clips), "build", "clips", progress)
    written = 0
    for (case, segment, *_), (_, records) in zip(jobs, map_jobs(render_base_clip, jobs, workers)):
        qas = [q for q in planned[base_clip_id(case, segment)] if q["qa_id"] not in done_qa]
        qa_log.append(paraphrase_qa(qas, paraphraser))
        clip_log.append(records)
        written += len(records)
        bar.update(len(records))
    bar.close()
    write_build_record(root, expected, complete=True)
    return {"root": str(root), "clips": expected["clips"], "written": written, "skipped": len(done_clips),
            "qa": expected["qa"]}


def read_build_record(root: str | Path) -> dict:
    """The parsed build.json of a clip set, or an error naming it and what it should hold."""
    return builds.read_build_record(root, "clips", "clip set", "task=build data=clips")


def build_kind(build: dict) -> str:
    """The suite kind a build record's plan names; "illusions" for a set built before suite kinds."""
    plan = build.get("plan") if isinstance(build.get("plan"), dict) else {}
    return check_kind(plan.get("kind", "illusions"))


# ---------------------------------------------------------------------------------------------- records

def read_lines(path: Path) -> Iterator[tuple[object, str]]:
    """(parsed JSON, "file:line") of every line of a JSON-lines file; an error naming the line that is not JSON."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: not found (a clip set has {CLIPS_FILE} and {QA_FILE})")
    with open(path, encoding="utf-8") as handle:
        for number, line in enumerate(handle, 1):
            try:
                yield json.loads(line), f"{path}:{number}"
            except json.JSONDecodeError as error:
                raise ValueError(f"{path}:{number}: not a JSON object ({error.msg})") from error


def check_clip_record(record, where: str) -> dict:
    """A clips.jsonl record (variant_records' form), else a ValueError naming `where` and the field."""
    if not isinstance(record, dict):
        raise ValueError(f"{where}: expected a clip object, got {type(record).__name__}")
    for field in ("clip_id", "base_clip_id", "case_id", "segment"):
        if not isinstance(record.get(field), str) or not record[field]:
            raise ValueError(f"{where}: {field}: expected a non-empty string, got {record.get(field)!r}")
    severity = record.get("severity")
    if isinstance(severity, bool) or not isinstance(severity, int) or not 0 <= severity <= 5:
        raise ValueError(f"{where}: severity: expected an integer from 0 (clean) to 5, got {severity!r}")
    for field in ("illusion", "category"):
        value = record.get(field, "absent")
        if (severity == 0) != (value is None) or not (value is None or isinstance(value, str)):
            raise ValueError(f"{where}: {field}: expected null for a clean clip (severity 0) and a name otherwise, "
                             f"got {value!r} at severity {severity}")
    if isinstance(record.get("seed"), bool) or not isinstance(record.get("seed"), int):
        raise ValueError(f"{where}: seed: expected an integer, got {record.get('seed')!r}")
    frames = record.get("frames")
    if not isinstance(frames, list) or len(frames) != 6 or not all(isinstance(f, str) and f for f in frames):
        raise ValueError(f"{where}: frames: expected a list of 6 image paths (relative to the set), got {frames!r}")
    return record


def check_every_question_asked(qas: Sequence[tuple[dict, str]], base_clip_ids: Sequence[str], source: str) -> None:
    """Every QA ((record, "file:line") pairs) names a base clip of the set (`base_clip_ids`, from `source`) and has
    a qa_id of its own among that clip's, else a ValueError naming the line, the id and the nearest ids: such a
    question would never be asked, or its answer would overwrite another's."""
    bases, seen = set(base_clip_ids), {}
    for qa, where in qas:
        base = qa["base_clip_id"]
        if base not in bases:
            near = difflib.get_close_matches(base, sorted(bases), n=3, cutoff=0.0)
            strays = sum(q["base_clip_id"] not in bases for q, _ in qas)
            raise ValueError(f"{where}: base_clip_id {base!r} names no clip of {source}, so QA {qa['qa_id']!r} would "
                             f"never be asked; nearest base clip ids: {', '.join(near)}"
                             + (f" ({strays} QA lines name no clip)" if strays > 1 else ""))
        key = (base, qa["qa_id"])
        if key in seen:
            raise ValueError(f"{where}: qa_id {qa['qa_id']!r} of base clip {base!r} is given twice (first at "
                             f"{seen[key]}); expected one id per question of a clip, or one answer would overwrite "
                             f"the other")
        seen[key] = where


# ---------------------------------------------------------------------------------------------- datasets

def _meta(record: dict) -> dict:
    return {k: record[k] for k in META_KEYS}


class ClipSetDataset(Dataset):
    """A clip suite written by `task=build data=clips` (or read from a DriveLM JSON with `from_drivelm`).

    Refuses a set whose build.json is missing or not complete, a line of clips.jsonl / qa.jsonl that is not a
    good record (file:line named), a clip whose base clip has no QA, and frames missing on disk."""

    def __init__(self, root: str | Path):
        root = Path(root)
        if not (root / BUILD_FILE).is_file():
            raise FileNotFoundError(f"clip set {root}: no {BUILD_FILE} (not a directory written by task=build "
                                    f"data=clips, or the build never started)")
        build = read_build_record(root)
        clips = [check_clip_record(r, where) for r, where in read_lines(root / CLIPS_FILE)]
        qas = [(check_qa_record(r, where), where) for r, where in read_lines(root / QA_FILE)]
        if not build["complete"] or len(clips) != build["clips"]:
            raise ValueError(f"clip set {root} is incomplete: {len(clips)} of {build['clips']} clips were built "
                             f"({BUILD_FILE} complete: {str(build['complete']).lower()}); rerun task=build "
                             f"data=clips with the same out_dir ({root}) to finish it")
        self._setup(root, clips, qas, str(root / CLIPS_FILE))
        self.kind = build_kind(build)

    @classmethod
    def from_drivelm(cls, path: str | Path, image_root: str | Path | None = None) -> "ClipSetDataset":
        """A dataset from a DriveLM-style QA JSON (vlm/clips/drivelm.py says which images make a clip); image paths
        are relative to `image_root` (default: the JSON file's folder)."""
        from lanevil_train.vlm.clips.drivelm import read_drivelm

        clips, qas = read_drivelm(path)
        self = cls.__new__(cls)
        self._setup(Path(image_root) if image_root is not None else Path(path).parent, clips,
                    [(qa, f"{path}: QA {qa['qa_id']}") for qa in qas], str(path))
        return self

    def _setup(self, root: Path, clips: list[dict], qas: list[tuple[dict, str]], source: str) -> None:
        """Keep the clips and their QA ((record, where it was read) pairs); refuse a set where a question would
        not be asked (its base clip missing, or its qa_id given twice), a base clip without QA, or missing frames."""
        if not clips:
            raise ValueError(f"{source}: the clip set lists no clips")
        self.root, self.clips, self.kind = root, clips, "illusions"
        check_every_question_asked(qas, [c["base_clip_id"] for c in clips], source)
        self.qa: dict[str, list[dict]] = {}
        for qa, _ in qas:
            self.qa.setdefault(qa["base_clip_id"], []).append(qa)
        no_qa = sorted({c["base_clip_id"] for c in clips} - set(self.qa))
        if no_qa:
            raise ValueError(f"{source}: {len(no_qa)} base clips have no QA, e.g. {no_qa[0]}")
        missing = [str(root / p) for c in clips for p in c["frames"] if not (root / p).is_file()]
        if missing:
            raise FileNotFoundError(f"{source}: {len(missing)} frame files are missing under {root}, e.g. "
                                    f"{', '.join(missing[:3])}")

    def __len__(self) -> int:
        return len(self.clips)

    def description(self) -> dict:
        """Where each clip variant's frames are (absolute paths), for the report page (per_answer.suite.json)."""
        return {"suite": "clip_frames", "frames": {c["clip_id"]: [str(self.root / p) for p in c["frames"]]
                                                  for c in self.clips}}

    def item_key(self, index: int) -> str:
        return self.clips[index]["clip_id"]

    def clip_meta(self, index: int) -> dict:
        return _meta(self.clips[index])

    def qa_for(self, base_clip_id: str) -> list[dict]:
        if base_clip_id not in self.qa:
            raise KeyError(f"no QA for base clip {base_clip_id!r} in {self.root}")
        return self.qa[base_clip_id]

    def __getitem__(self, index: int) -> dict:
        record = self.clips[index]
        frames = [load_image(self.root / p) for p in record["frames"]]
        return {"frames": frames, "qa": self.qa_for(record["base_clip_id"]), "meta": _meta(record)}


class SyntheticClipSuite(Dataset):
    """The suite `task=build data=clips` would write, rendered on the fly (nothing on disk). Items run base
    clip by base clip (clean first); a base clip renders all its variants at once, and the renders of the last
    `cache_clips` base clips are kept, so an unshuffled pass (or qa_data.WindowShuffleSampler with a window of at
    most `cache_clips`) renders each base clip once. `kind` is the suite kind; `illusions` its names (the
    corruptions of a corruption suite)."""

    def __init__(self, num_cases: int, first_seed: int, illusions: str | Sequence[str] = "all",
                 severities: Sequence[int] = (1, 2, 3, 4, 5), size: Sequence[int] = (360, 640), per_clip: int = 5,
                 cache_clips: int = 1, kind: str = "illusions"):
        if not isinstance(num_cases, int) or num_cases < 1:
            raise ValueError(f"num_cases: expected an integer >= 1, got {num_cases!r}")
        if isinstance(cache_clips, bool) or not isinstance(cache_clips, int) or cache_clips < 1:
            raise ValueError(f"cache_clips: expected an integer >= 1 (base clips whose renders are kept), "
                             f"got {cache_clips!r}")
        if check_kind(kind) == "illusions":
            names = list(ILLUSION_NAMES) if illusions == "all" else list(illusions)
            if not names:
                raise ValueError("illusions: expected 'all' or a non-empty list of illusion names, got an empty list")
            self.cases = _geometry().clip_cases(num_cases, first_seed, names)
        else:
            names = list(suite_names(kind, illusions))
            self.cases = _geometry().suite_cases(kind, num_cases, first_seed, names)
        self.kind, self.names = kind, tuple(names)
        self.severities, self.size, self.per_clip = tuple(severities), tuple(size), per_clip
        _check_build_arguments(self.cases, self.severities, self.size, kind, self.names)
        self.items = [(case, segment, record) for case, segment in suite_base_clips(self.cases, kind, per_clip)
                      for record in variant_records(case, segment, self.severities, kind, self.names)]
        self.by_base = {base_clip_id(case, segment): (case, segment) for case, segment, _ in self.items}
        self._truths: dict[str, dict] = {}
        self._planned: dict[str, list[dict]] | None = None
        self.cache_clips = cache_clips
        self._renders: OrderedDict[tuple, dict] = OrderedDict()  # (case, segment) -> severity -> frames, LRU
        self._arguments = {"num_cases": num_cases, "first_seed": first_seed,
                           "illusions": illusions if isinstance(illusions, str) else list(illusions),
                           "severities": list(self.severities), "size": list(self.size), "per_clip": per_clip,
                           "kind": kind}

    def description(self) -> dict:
        """What rebuilds this suite (from_description): its constructor's arguments, as JSON values. An evaluation
        writes it beside its results (per_answer.suite.json), so the report page can render a clip's frames again."""
        return {"suite": "synthetic_clips", **self._arguments}

    @classmethod
    def from_description(cls, description: dict) -> "SyntheticClipSuite":
        """The suite a description() names."""
        args = {k: v for k, v in description.items() if k != "suite"}
        return cls(args["num_cases"], args["first_seed"], args["illusions"], tuple(args["severities"]),
                   tuple(args["size"]), args["per_clip"], kind=args["kind"])

    def __len__(self) -> int:
        return len(self.items)

    def item_key(self, index: int) -> str:
        return self.items[index][2]["clip_id"]

    def clip_meta(self, index: int) -> dict:
        return _meta(self.items[index][2])

    def qa_for(self, base_clip_id: str) -> list[dict]:
        """The base clip's QA, planned with every other base clip's of the suite (the first call computes the truth
        of those not yet prepared)."""
        self._base(base_clip_id)
        return self.plan()[base_clip_id]

    def plan(self, workers: int = 0, progress: str = "auto") -> dict[str, list[dict]]:
        """{base clip id: its QA} of the whole suite (computed once; the truths not yet known in `workers`
        processes)."""
        if self._planned is None:
            bases = list(dict.fromkeys((case, segment) for case, segment, _ in self.items))
            self._planned = plan_qa(bases, self.size, self.per_clip, self.kind, workers, progress, self._truths)
        return self._planned

    def qa_count(self, base_clip_id: str) -> int:
        """How many QA the base clip has (per_clip, less those a corruption suite leaves out), without its truth."""
        if base_clip_id not in self.by_base:
            raise KeyError(f"no base clip {base_clip_id!r} in this synthetic suite")
        case, segment = self.by_base[base_clip_id]
        return len(kept_questions(self.kind, case.seed, segment, self.per_clip))

    def training_aids_for(self, base_clip_id: str) -> list[dict]:
        """The base clip's training-only QA (qa.training_aids: the scene description and the open questions that
        name its facts): a suite on disk has no truth."""
        return training_aids(self._truth(base_clip_id), base_clip_id)

    def scene_classes_for(self, base_clip_id: str) -> list[int]:
        """The base clip's scene truth as class indices (qa.scene_classes): what the embedded VLM's vision tower is
        pretrained on."""
        return scene_classes(self._truth(base_clip_id), base_clip_id)

    def lanes_for(self, base_clip_id: str) -> list[list[list[list[float]]]]:
        """The lane polylines ([x, y] pixels at the suite's frame size) of each of the base clip's frames: every
        variant's ground truth, as illusions never move a lane (AAM's lanes on a VLM's frames)."""
        return self._truth(base_clip_id)["lanes_px"]

    def _truth(self, base_clip_id: str) -> dict:
        """The base clip's scene truth (computed once)."""
        if base_clip_id not in self._truths:
            case, segment = self._base(base_clip_id)
            self._truths[base_clip_id] = _geometry().clip_truth(case, segment, size=self.size)
        return self._truths[base_clip_id]

    def _base(self, base_clip_id: str) -> tuple:
        if base_clip_id not in self.by_base:
            raise KeyError(f"no base clip {base_clip_id!r} in this synthetic suite")
        return self.by_base[base_clip_id]

    def prepare(self, base_clip_ids: Sequence[str], render: Sequence[str] = (), workers: int = 0,
                progress: str = "auto") -> dict[str, list[list[np.ndarray]]]:
        """Compute the truth of the base clips `base_clip_ids` and render those also in `render`, all in `workers`
        processes (0: in this one), then plan the suite's QA (so qa_for, training_aids_for, scene_classes_for and
        lanes_for compute nothing more); {base clip id: the frames of each of its variants, in item order}, in
        `render`'s order. Frames and facts are those __getitem__ and qa_for give: frames and truth are functions of
        their case alone, the QA of the suite."""
        for base in base_clip_ids:
            self._base(base)
        stray = sorted(set(render) - set(base_clip_ids))
        if stray:
            raise ValueError(f"render: expected base clips among base_clip_ids, got {stray[:3]}")
        variants: dict[str, list[tuple]] = {base: [] for base in render}
        for _, _, record in self.items:
            if record["base_clip_id"] in variants:
                variants[record["base_clip_id"]].append((record["illusion"], record["severity"]))
        jobs = [(*self.by_base[base], self.severities, self.size, self.kind, self.names, base in variants)
                for base in base_clip_ids]
        bar = progress_counter(len(jobs), desc="scene truth and frames", unit="base clip", mode=progress)
        rendered = {}
        for base, (renders, truth) in zip(base_clip_ids, map_jobs(render_with_truth, jobs, workers)):
            self._truths[base] = truth
            if renders is not None:
                rendered[base] = [list(renders[key]) for key in variants[base]]
            bar.update(1)
        bar.close()
        self.plan(workers, progress)  # the QA of the clips asked: planned with the whole suite's
        return {base: rendered[base] for base in variants}

    def __getitem__(self, index: int) -> dict:
        case, segment, record = self.items[index]
        key = (case, segment)
        if key in self._renders:
            self._renders.move_to_end(key)
        else:
            self._renders[key] = _render(case, segment, self.severities, self.size, self.kind, self.names)
            while len(self._renders) > self.cache_clips:
                self._renders.popitem(last=False)
        frames = list(self._renders[key][(record["illusion"], record["severity"])])
        return {"frames": frames, "qa": self.qa_for(record["base_clip_id"]), "meta": _meta(record)}
