"""Scoring a VLM's answers: a model's answers to a clip suite logged and scored (evaluation.py), and the judges that
rate an open answer against its reference (judge.py: an LLM judge, an offline sentence-embedding judge)."""
