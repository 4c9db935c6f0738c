"""The VLM tasks (model.kind=vlm): train (fine-tuning, and the textual defenses' tuning), evaluate, and the wiring
they share (builders.py). They never import the detector tasks; what both kinds share is in tasks/builders.py."""
