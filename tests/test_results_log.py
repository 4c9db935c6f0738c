"""ResultsLog: finished keys survive an interruption, a torn last line is cut, a corrupt middle line is named."""

from __future__ import annotations

import json

import pytest

from lanevil_train.results_log import ResultsLog


def test_resume_cuts_a_torn_tail_and_lists_finished_keys(tmp_path):
    log = ResultsLog(tmp_path / "sub" / "r.jsonl")
    assert log.resume() == set()  # parent folder made, nothing finished
    log.append([{"key": "a", "v": 1}, {"key": "b", "v": 2}])
    with open(log.path, "a") as handle:
        handle.write('{"key": "c", "v"')  # killed mid-write
    assert [r["key"] for r in log.records()] == ["a", "b"]  # the torn tail is not a record
    assert log.resume() == {"a", "b"}
    log.append([{"key": "c", "v": 3}])
    assert [json.loads(line)["key"] for line in log.path.read_text().splitlines()] == ["a", "b", "c"]


def test_records_drop_fields_except_for_chosen_keys(tmp_path):
    log = ResultsLog(tmp_path / "r.jsonl")
    log.append([{"key": "a", "big": [1, 2], "v": 1}, {"key": "b", "big": [3], "v": 2}])
    assert log.records(drop=("big",), keep_for={"b"}) == [{"key": "a", "v": 1}, {"key": "b", "big": [3], "v": 2}]


def test_bad_input_is_named(tmp_path):
    log = ResultsLog(tmp_path / "r.jsonl")
    with pytest.raises(ValueError, match=r"r.jsonl: a result record needs a 'key'"):
        log.append([{"v": 1}])
    log.path.write_text('{"key": "a"}\nnot json\n{"key": "b"}\n')
    with pytest.raises(ValueError, match=r"r.jsonl:2: not a JSON object"):
        log.records()
    log.path.write_text('{"key": "a"}\n[1, 2]\n')
    with pytest.raises(ValueError, match=r"r.jsonl:2: expected a JSON object, got list"):
        log.records()
