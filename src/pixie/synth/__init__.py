"""Synthetic data: procedural parts, photo-like renders, labelled query/reference pairs."""
