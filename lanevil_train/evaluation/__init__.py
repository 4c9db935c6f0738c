"""Scoring lane detectors, below the task wiring: one record per image (lane_records.py), the streaming, resumable
evaluation of a dataset (streaming.py), and the score tables built from the records (results.py)."""
