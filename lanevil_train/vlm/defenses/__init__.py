"""The textual defenses of a VLM: PAT++'s tuned defense prefix (pat.py), its PAT baseline (pat_baseline.py), the
greedy coordinate gradient steps both tune with (gcg.py), and Self-Reminder (reminder.py)."""
