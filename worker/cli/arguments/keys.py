"""``osdar-ar keys`` (API keys) and ``osdar-ar migrate`` (the database)."""

from __future__ import annotations

import argparse


def _add_keys(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("keys", help="manage API keys of the job service")
    keys = p.add_subparsers(dest="keys_command", required=True)
    c = keys.add_parser("create", help="create a key and print its secret (shown once)")
    c.add_argument("name", help="who or what the key is for")
    c.add_argument("--operator", action="store_true",
                   help="an operator key: the dashboard shows it every key's jobs and "
                   "campaigns, the workers, the queue depth and the failure rate")  # fmt: skip
    keys.add_parser("list", help="list keys (id, prefix, role, state, name)")
    r = keys.add_parser("revoke", help="revoke a key by id")
    r.add_argument("key_id", type=int)
    g = keys.add_parser("grant-operator", help="make a key an operator (by id)")
    g.add_argument("key_id", type=int)
    g.add_argument("--revoke", action="store_true", help="take the operator role away")
    p.set_defaults(command_group="keys")


def _add_migrate(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "migrate",
        help="apply the database migrations (alembic upgrade head): the prestart step",
    )
    p.add_argument("--revision", default="head")
    p.set_defaults(command_group="keys")


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """The sub-commands ``keys`` and ``migrate``."""
    _add_keys(sub)
    _add_migrate(sub)
