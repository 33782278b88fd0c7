"""Reliability and security scenarios (RELIABILITY.md), one module each; see common.py."""
