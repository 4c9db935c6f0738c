"""Driving vision-language models: one interface (vlm/base.py) and its backends, clips and QA from the simulator,
and (later) PAT++. Backends import their heavy libraries (transformers, HTTP) only when built."""
