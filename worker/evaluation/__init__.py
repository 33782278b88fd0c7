"""Evaluation (pipeline step 8): the paper's RPE and jitter, true pose errors, and the
placed object's error against a render with the true poses."""
