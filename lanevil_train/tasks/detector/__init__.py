"""The lane-detector tasks (model.kind=detector): train, evaluate / cross_domain, export. They never import the VLM
tasks; what both kinds share is in tasks/builders.py."""
