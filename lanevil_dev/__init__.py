"""Development-only helpers of the source checkout: test doubles for this project's tests and benchmarks.

Not in the wheel (pyproject's packages.find takes only lanevil_train*), and nothing under lanevil_train/ imports it
(tests/test_packaging.py checks both). Importable from a source checkout: pytest puts the checkout root on sys.path
(pyproject's `pythonpath`), benchmarks/ scripts insert it themselves, FakeServer's process gets it on PYTHONPATH.

- fake_server: a local OpenAI-compatible server process (deterministic answers, injectable failures), FakeServer;
  `python -m lanevil_dev.fake_server` from the checkout root.
- tiny_vlm: tiny random-weight Hugging Face VLMs of every family, built offline (build_tiny_vlm, make_tiny_vlm,
  FAMILIES).
"""
