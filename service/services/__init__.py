"""Keyword-only service functions: the logic behind the routes, tested directly."""
