"""Test doubles that ship with the package, for this project's tests and for users testing their own code against
ours: `fake_server`, a local OpenAI-compatible server process (deterministic answers, injectable failures)."""
