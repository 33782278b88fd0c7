"""Synthetic digital twin: OSDaR23-layout sequences with ground truth."""
