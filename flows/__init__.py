"""Prefect flows: wiring only, each task one pipeline call."""
