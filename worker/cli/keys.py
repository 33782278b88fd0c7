"""``osdar-ar keys`` (create, list, revoke API keys of the job service) and ``osdar-ar
migrate`` (the database schema to a revision)."""

from __future__ import annotations

import argparse
import logging
import sys

from sqlalchemy import select
from sqlalchemy.exc import SQLAlchemyError

from osdar_platform.db import session_scope
from osdar_platform.keys import create_api_key, revoke_api_key, set_operator
from osdar_platform.migrate import upgrade
from osdar_platform.models import ApiKey
from osdar_platform.settings import Settings, get_settings
from worker.cli.errors import CliError

log = logging.getLogger("osdar_ar")


def _database_ready() -> Settings:
    """The settings, with the database migrated to head first (idempotent): a command that
    needs the tables works on a fresh database, or says in one line why it cannot."""
    settings = get_settings()
    try:
        upgrade(database_url=str(settings.database_url))
    except (SQLAlchemyError, OSError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise CliError(
            f"database {settings.database_url} is not usable ({first}); check DATABASE_URL "
            "and run `osdar-ar migrate`"
        ) from exc
    return settings


def create(args: argparse.Namespace) -> int:
    settings = _database_ready()
    try:
        with session_scope(settings) as session:
            row, secret = create_api_key(
                session=session,
                name=args.name,
                pepper=settings.api_key_pepper.get_secret_value(),
                operator=args.operator,
            )
            key_id = row.id
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    role = " operator" if args.operator else ""
    print(f"key {key_id} ({args.name}){role}; the secret is shown only now:", file=sys.stderr)  # noqa: T201
    print(secret)  # noqa: T201 - CLI output
    return 0


def list_keys(args: argparse.Namespace) -> int:
    with session_scope(_database_ready()) as session:
        for k in session.scalars(select(ApiKey).order_by(ApiKey.id)):
            state = "revoked" if k.revoked else "active"
            role = "operator" if k.operator else "key"
            print(f"{k.id:>5}  {k.prefix}...  {role:<8} {state:<8} {k.name}")  # noqa: T201
    return 0


def revoke(args: argparse.Namespace) -> int:
    with session_scope(_database_ready()) as session:
        if not revoke_api_key(session=session, key_id=args.key_id):
            raise CliError(f"no key with id {args.key_id}")
    return 0


def grant_operator(args: argparse.Namespace) -> int:
    with session_scope(_database_ready()) as session:
        if not set_operator(session=session, key_id=args.key_id, operator=not args.revoke):
            raise CliError(f"no key with id {args.key_id}")
    how = "no longer an operator" if args.revoke else "an operator"
    print(f"key {args.key_id} is {how}", file=sys.stderr)  # noqa: T201 - CLI output
    return 0


def migrate(args: argparse.Namespace) -> int:
    url = str(get_settings().database_url)
    upgrade(database_url=url, revision=args.revision)
    log.info("database at revision %s", args.revision)
    return 0


def run(args: argparse.Namespace) -> int:
    if args.command == "migrate":
        return migrate(args)
    commands = {
        "create": create,
        "list": list_keys,
        "revoke": revoke,
        "grant-operator": grant_operator,
    }
    return commands[args.keys_command](args)
