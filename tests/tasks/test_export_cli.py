"""task=export writes the network as ONNX, and task=evaluate task.onnx=... scores it like the checkpoint."""

from __future__ import annotations

import json

import numpy as np
import onnx
import pytest

from lanevil_train.evaluation.lane_records import read_records
from tests.tasks.cli_helpers import TINY, run_in_process


def test_export_then_evaluate_the_onnx_model_gives_the_checkpoints_scores(tmp_path):
    train_dir = tmp_path / "train"
    run_in_process([*TINY, "model=scnn", "trainer.max_steps=3", "trainer.limit_val_batches=1", "trainer.max_epochs=10",
                    "logger=none"], train_dir)
    last = train_dir / "checkpoints" / "last.ckpt"
    out = tmp_path / "export" / "model.onnx"
    worst = run_in_process(["task=export", f"ckpt_path={last}", f"task.out={out}"], tmp_path / "export_run")
    assert worst <= 1e-4
    graph = onnx.load(str(out))
    meta = {p.key: p.value for p in graph.metadata_props}
    assert json.loads(meta["lanevil_model"])["input_size"] == [64, 160]
    assert graph.graph.input[0].type.tensor_type.shape.dim[0].dim_param == "batch"  # any batch size
    assert not list(tmp_path.glob("export/.*partial"))  # written atomically

    # an early checkpoint: no thresholds, so every lane slot is decoded (SCNN's options, added with a +)
    decode = ["+task.decode.exist_threshold=0.0", "+task.decode.prob_threshold=0.0"]
    run_in_process(["task=evaluate", f"ckpt_path={last}", *decode, *TINY], tmp_path / "eval_pt")
    run_in_process(["task=evaluate", f"task.onnx={out}", *decode, *TINY], tmp_path / "eval_onnx")
    by_torch = read_records(tmp_path / "eval_pt" / "per_image.jsonl")
    by_onnx = read_records(tmp_path / "eval_onnx" / "per_image.jsonl")
    assert len(by_torch) == len(by_onnx) == 4
    assert sum(r["num_pred"] for r in by_torch) > 0
    for a, b in zip(by_torch, by_onnx):
        assert a["case_id"] == b["case_id"] and a["num_pred"] == b["num_pred"]
        assert a["accuracy"] == pytest.approx(b["accuracy"]) and a["fp"] == b["fp"] and a["fn"] == b["fn"]
        # the same lanes; an untrained SCNN's nearly flat probability maps can tie two columns, and a 1e-7
        # difference between onnxruntime and torch then moves a point one column (1 px here)
        assert np.allclose(np.asarray(a["pred_lanes"], float), np.asarray(b["pred_lanes"], float), atol=1.0)
    scores = [json.loads((tmp_path / d / "test_scores.json").read_text())[0] for d in ("eval_pt", "eval_onnx")]
    for key in ("Accuracy", "FP", "FN", "F1"):
        assert scores[0][key] == pytest.approx(scores[1][key], abs=1e-9), key


def test_export_without_checkpoint_and_bad_onnx_files(tmp_path):
    out = tmp_path / "random.onnx"
    run_in_process(["task=export", "model=clrnet", "data.input_size=[64,160]", f"task.out={out}"], tmp_path / "run")
    meta = {p.key: p.value for p in onnx.load(str(out)).metadata_props}
    assert json.loads(meta["lanevil_model"])["model"]["name"] == "clrnet"
    plain = tmp_path / "plain.onnx"
    h = onnx.helper
    value = h.make_tensor_value_info("images", onnx.TensorProto.FLOAT, [1, 3, 64, 160])
    out_value = h.make_tensor_value_info("out", onnx.TensorProto.FLOAT, [1, 3, 64, 160])
    graph = h.make_graph([h.make_node("Identity", ["images"], ["out"])], "g", [value], [out_value])
    onnx.save(h.make_model(graph, opset_imports=[h.make_opsetid("", 17)]), str(plain))  # a valid model, not ours
    with pytest.raises(ValueError, match="plain.onnx: no 'lanevil_model' metadata; "
                                         "expected an ONNX model written by task=export"):
        run_in_process(["task=evaluate", f"task.onnx={plain}", *TINY], tmp_path / "eval")
    with pytest.raises(ValueError, match="task.onnx: expected null or the path of an existing ONNX model"):
        run_in_process(["task=evaluate", f"task.onnx={tmp_path / 'none.onnx'}", *TINY], tmp_path / "eval")
