"""API keys: a random secret shown once, stored as a peppered SHA-256.

The secret is ``oar_<43 url-safe chars>`` (256 bits); the table keeps its hash and its
first characters (``prefix``) so that an operator can tell keys apart. With 256-bit random
secrets a fast hash is enough (no dictionary to attack); the pepper, kept out of the
database, makes a stolen table useless on its own.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets

from sqlalchemy import select
from sqlalchemy.orm import Session

from osdar_platform.models import ApiKey

SECRET_PREFIX = "oar_"
PREFIX_CHARS = 12


def generate_secret() -> str:
    return SECRET_PREFIX + secrets.token_urlsafe(32)


def hash_secret(secret: str, pepper: str) -> str:
    """Hex SHA-256 of the pepper and the secret (HMAC construction)."""
    return hmac.new(pepper.encode(), secret.encode(), hashlib.sha256).hexdigest()


def create_api_key(
    *, session: Session, name: str, pepper: str, operator: bool = False
) -> tuple[ApiKey, str]:
    """Add a key (flushed, not committed); returns the row and the secret (shown once).
    ``operator``: the dashboard shows it everyone's jobs and campaigns and the workers."""
    name = name.strip()
    if not name or len(name) > 200:
        raise ValueError("key name must be 1..200 characters")
    secret = generate_secret()
    row = ApiKey(
        name=name,
        key_hash=hash_secret(secret, pepper),
        prefix=secret[:PREFIX_CHARS],
        operator=operator,
    )
    session.add(row)
    session.flush()
    return row, secret


def find_api_key(*, session: Session, secret: str, pepper: str) -> ApiKey | None:
    """The active key whose hash matches ``secret``, or None."""
    if not secret or len(secret) > 256:
        return None
    digest = hash_secret(secret, pepper)
    return session.scalar(
        select(ApiKey).where(ApiKey.key_hash == digest, ApiKey.revoked.is_(False))
    )


def revoke_api_key(*, session: Session, key_id: int) -> bool:
    row = session.get(ApiKey, key_id)
    if row is None:
        return False
    row.revoked = True
    return True


def set_operator(*, session: Session, key_id: int, operator: bool = True) -> bool:
    """Grant (or take away) the operator role; False when there is no such key."""
    row = session.get(ApiKey, key_id)
    if row is None:
        return False
    row.operator = operator
    return True
