"""DriveLM-nuScenes QA JSON: write a clip suite's QA in that layout, and read a DriveLM-style file back as clips + QA.

Layout (DriveLM docs/data_prep_nus.md): {scene_token: {"scene_description", "key_frames": {frame_token:
{"key_object_infos", "QA": {"perception": [...], "prediction": [...], "planning": [...], "behavior": [...]},
"image_paths": {...}}}}}, each QA item {"Q", "A", "C", "con_up", "con_down", "cluster", "layer"}.

Writing: a scene is a case, a key frame is a base clip; `image_paths` holds the clean clip's 6 frames as FRAME_0 ..
FRAME_5; our six categories go to DriveLM's four (CATEGORY_TO_DRIVELM), a choice question's options are appended
to "Q" as DriveLM's multiple-choice questions have them, and each item keeps our record in "lanevil" and each key
frame its clip variants in "lanevil_clips" and its QA order in "lanevil_qa_order", so `read_drivelm(write_drivelm(...))`
gives back the same records.

Reading a DriveLM file (or a user's in that layout) without those fields: a key frame is one clean clip
(clip_id = base_clip_id = frame token, case_id = scene token, segment "key_frame", severity 0). A DriveLM key frame
has camera views, not 6 consecutive frames: its 6 nuScenes cameras are taken as the 6 images in NUSCENES_CAMERAS
order (front-left, front, front-right, back-right, back, back-left); image_paths with FRAME_<k> keys are taken in
k order; fewer than 6 paths are padded by repeating the last one. A section's items get the section's category
(DRIVELM_TO_CATEGORY); type: "choice" when "Q" lists lettered options, "yes_no" when "A" starts with yes/no, else
"open". Image paths are kept as written (relative ones are resolved by the reader of the images, e.g.
ClipSetDataset.from_drivelm's image_root).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

from lanevil_train.files.atomic import atomic_write_text
from lanevil_train.vlm.clips.qa_records import OPTIONS_LEAD, check_qa_record, prompt_text

SECTIONS = ("perception", "prediction", "planning", "behavior")
CATEGORY_TO_DRIVELM = {"scene_description": "perception", "object_recognition": "perception",
                       "lane_recognition": "perception", "object_behavior": "prediction",
                       "motion_reasoning": "behavior", "action": "planning"}
DRIVELM_TO_CATEGORY = {"perception": "object_recognition", "prediction": "object_behavior",
                       "planning": "action", "behavior": "motion_reasoning"}
NUSCENES_CAMERAS = ("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT")
_OPTION = re.compile(r"(?:^|\s)([A-Z])\.\s+(.*?)(?=\s+[A-Z]\.\s|$)", re.DOTALL)


def _item(qa: dict) -> dict:
    """One DriveLM QA item for our QA record (ours kept whole under "lanevil"), with the tags DriveLM's evaluation
    scores it by (challenge/evaluation.py: 0 accuracy for yes/no and choice, 1 GPT and 2 language for open)."""
    tag = qa.get("drivelm_tag") or ([0] if qa["type"] != "open" else [1, 2])
    return {"Q": prompt_text(qa), "A": qa["answer"], "C": None, "con_up": None, "con_down": None, "cluster": None,
            "layer": None, "tag": list(tag), "lanevil": dict(qa)}


def _tags(item: dict, where: str) -> dict:
    """{"drivelm_tag": [...]} from a DriveLM item's "tag" (the parts of DriveLM's score it counts in), or {}."""
    tag = item.get("tag")
    if tag is None:
        return {}
    tags = [tag] if isinstance(tag, int) and not isinstance(tag, bool) else tag
    if not isinstance(tags, list) or not all(isinstance(t, int) and not isinstance(t, bool) and 0 <= t <= 3
                                             for t in tags):
        raise ValueError(f"{where}: tag: expected a list of DriveLM score tags 0 (accuracy), 1 (GPT), 2 (language), "
                         f"3 (match), got {tag!r}")
    return {"drivelm_tag": list(tags)}


def to_drivelm(clips: list[dict], qas: list[dict]) -> dict:
    """The DriveLM layout of a suite's clip records (clips.jsonl) and QA records (qa.jsonl)."""
    out: dict = {}
    frames: dict[str, dict] = {}
    by_base: dict[str, list[dict]] = {}
    for clip in clips:
        by_base.setdefault(clip["base_clip_id"], []).append(clip)
    for base, variants in by_base.items():
        clean = next((c for c in variants if c["severity"] == 0), None)
        if clean is None:
            raise ValueError(f"base clip {base}: no clean clip (severity 0) among its {len(variants)} variants; a "
                             f"DriveLM key frame's image_paths are the clean clip's frames")
        scene = out.setdefault(clean["case_id"], {"scene_description": "", "key_frames": {}})
        frames[base] = scene["key_frames"][base] = {
            "key_object_infos": {}, "QA": {s: [] for s in SECTIONS},
            "image_paths": {f"FRAME_{k}": p for k, p in enumerate(clean["frames"])},
            "lanevil_clips": variants, "lanevil_qa_order": []}
    for i, qa in enumerate(qas):
        check_qa_record(qa, f"QA {i} ({qa.get('qa_id') if isinstance(qa, dict) else '?'})")
        frame = frames.get(qa["base_clip_id"])
        if frame is None:
            raise ValueError(f"QA {qa['qa_id']}: base_clip_id {qa['base_clip_id']!r} is not a clip of this suite")
        frame["QA"][CATEGORY_TO_DRIVELM[qa["category"]]].append(_item(qa))
        frame["lanevil_qa_order"].append(qa["qa_id"])
    return out


def write_drivelm(path: str | Path, clips: list[dict], qas: list[dict]) -> None:
    """Write the suite's QA as a DriveLM-nuScenes JSON file (atomically)."""
    atomic_write_text(path, json.dumps(to_drivelm(clips, qas), indent=1) + "\n")


# ---------------------------------------------------------------------------------------------- reading

def _frames(image_paths, where: str) -> list[str]:
    """The 6 image paths a key frame's image_paths give (see the module doc for which and in what order)."""
    if isinstance(image_paths, list):
        paths = list(image_paths)
    elif isinstance(image_paths, dict):
        numbered = sorted((int(k.split("_", 1)[1]), v) for k, v in image_paths.items()
                          if re.fullmatch(r"FRAME_\d+", str(k)))
        cameras = [image_paths[c] for c in NUSCENES_CAMERAS if c in image_paths]
        paths = [v for _, v in numbered] if numbered else cameras or list(image_paths.values())
    else:
        raise ValueError(f"{where}: image_paths: expected a mapping of camera or frame name to path, got "
                         f"{type(image_paths).__name__}")
    if not paths or not all(isinstance(p, str) and p for p in paths):
        raise ValueError(f"{where}: image_paths: expected 1 to 6 non-empty path strings, got {image_paths!r}")
    if len(paths) > 6:
        raise ValueError(f"{where}: image_paths: {len(paths)} images, a clip takes 6 (name them FRAME_0..FRAME_5 "
                         f"or the 6 nuScenes cameras)")
    return paths + [paths[-1]] * (6 - len(paths))


def _their_qa(item, where: str, qa_id: str, base: str, section: str) -> dict:
    """Our QA record for a DriveLM item that has no "lanevil" record."""
    if not isinstance(item, dict):
        raise ValueError(f"{where}: expected a QA object with Q and A, got {type(item).__name__}")
    for field in ("Q", "A"):
        if not isinstance(item.get(field), str) or not item[field].strip():
            raise ValueError(f"{where}: {field}: expected a non-empty string, got {item.get(field)!r}")
    question, answer = item["Q"].strip(), item["A"].strip()
    record = {"qa_id": qa_id, "base_clip_id": base, "category": DRIVELM_TO_CATEGORY[section], **_tags(item, where)}
    options = _OPTION.findall(question)
    if len(options) >= 2 and re.match(r"^\(?[A-Z]\b", answer):
        first = re.search(r"(?:^|\s)A\.\s", question)
        stem = question[: first.start()].strip() if first else question
        stem = stem.replace(OPTIONS_LEAD.strip(), "").strip() or question
        letter = answer.lstrip("(")[0]
        choices = [f"{k}. {v.strip()}" for k, v in options]
        full = next((c for c in choices if c.startswith(letter + ".")), letter)
        return {**record, "type": "choice", "question": stem, "answer": full, "choices": choices}
    kind = "yes_no" if re.match(r"^(yes|no)\b", answer, re.IGNORECASE) else "open"
    return {**record, "type": kind, "question": question, "answer": answer}


def _read_frame(scene_token: str, token: str, frame, where: str) -> tuple[list[dict], list[dict]]:
    if not isinstance(frame, dict) or not isinstance(frame.get("QA"), dict) or "image_paths" not in frame:
        missing = "QA" if not isinstance(frame, dict) or not isinstance(frame.get("QA"), dict) else "image_paths"
        raise ValueError(f"{where}: missing {missing!r} (a key frame has QA by section and image_paths)")
    if "lanevil_clips" in frame:
        clips = frame["lanevil_clips"]
    else:
        clips = [{"clip_id": token, "base_clip_id": token, "case_id": scene_token, "segment": "key_frame",
                  "illusion": None, "category": None, "severity": 0, "seed": 0,
                  "frames": _frames(frame["image_paths"], where)}]
    qas = []
    for section, items in frame["QA"].items():
        if section not in SECTIONS:
            raise ValueError(f"{where}: QA.{section}: unknown section; expected {', '.join(SECTIONS)}")
        if not isinstance(items, list):
            raise ValueError(f"{where}: QA.{section}: expected a list of QA items, got {type(items).__name__}")
        for i, item in enumerate(items):
            at = f"{where}: QA.{section}[{i}]"
            ours = item.get("lanevil") if isinstance(item, dict) else None
            qa = dict(ours) if ours is not None else _their_qa(item, at, f"{token}-{section}-{i}", token, section)
            qas.append(check_qa_record(qa, at))
    order = {qa_id: i for i, qa_id in enumerate(frame.get("lanevil_qa_order", []))}
    return clips, sorted(qas, key=lambda qa: order.get(qa["qa_id"], len(order)))


def read_drivelm(path: str | Path) -> tuple[list[dict], list[dict]]:
    """(clip records, QA records) of a DriveLM-style QA JSON file; errors name the scene and frame token."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as error:
        raise ValueError(f"{path}: cannot read a DriveLM QA JSON ({error})") from error
    if not isinstance(data, dict) or not data:
        raise ValueError(f"{path}: expected a JSON object of scenes ({{scene_token: {{'key_frames': ...}}}}), got "
                         f"{type(data).__name__ if data else 'an empty one'}")
    clips, qas = [], []
    for scene_token, scene in data.items():
        if not isinstance(scene, dict) or not isinstance(scene.get("key_frames"), dict):
            raise ValueError(f"{path}: scene {scene_token}: missing 'key_frames' (a mapping of frame token to key "
                             f"frame)")
        for token, frame in scene["key_frames"].items():
            more_clips, more_qa = _read_frame(scene_token, token, frame, f"{path}: scene {scene_token} frame {token}")
            clips += more_clips
            qas += more_qa
    return clips, qas
