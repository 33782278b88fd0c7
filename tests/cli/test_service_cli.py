"""``osdar-ar migrate`` and ``osdar-ar keys``: the prestart step and the key helper."""

from __future__ import annotations

from pathlib import Path

import pytest
from sqlalchemy import select

from osdar_platform.settings import get_settings
from worker.cli import main


def test_migrate_then_create_list_revoke_a_key(
    fresh_data_dir: Path, capsys: pytest.CaptureFixture
) -> None:
    from osdar_platform.db import session_scope
    from osdar_platform.keys import find_api_key
    from osdar_platform.models import ApiKey

    assert main(["migrate"]) == 0
    assert (fresh_data_dir / "osdar-ar.db").is_file()
    assert main(["migrate"]) == 0  # idempotent
    capsys.readouterr()
    assert main(["keys", "create", "ci robot"]) == 0
    out = capsys.readouterr()
    secret = out.out.strip()
    assert secret.startswith("oar_") and len(secret) > 40 and "shown only now" in out.err
    settings = get_settings()
    pepper = settings.api_key_pepper.get_secret_value()
    with session_scope(settings) as s:
        (row,) = s.scalars(select(ApiKey)).all()
        assert row.name == "ci robot" and secret not in row.key_hash
        assert find_api_key(session=s, secret=secret, pepper=pepper) is not None
    assert main(["keys", "list"]) == 0
    assert "ci robot" in capsys.readouterr().out
    assert main(["keys", "revoke", str(row.id)]) == 0
    with session_scope(settings) as s:
        assert find_api_key(session=s, secret=secret, pepper=pepper) is None
    assert main(["keys", "revoke", "999"]) == 2
    assert main(["keys", "create", " "]) == 2


def test_operator_keys_are_created_and_granted_by_the_cli(
    fresh_data_dir: Path, capsys: pytest.CaptureFixture
) -> None:
    from osdar_platform.db import session_scope
    from osdar_platform.models import ApiKey

    assert main(["keys", "create", "ops", "--operator"]) == 0
    assert "operator" in capsys.readouterr().err
    assert main(["keys", "create", "alice"]) == 0
    with session_scope(get_settings()) as s:
        roles = {k.name: (k.id, k.operator) for k in s.scalars(select(ApiKey))}
    assert roles["ops"][1] is True and roles["alice"][1] is False
    assert main(["keys", "grant-operator", str(roles["alice"][0])]) == 0
    assert main(["keys", "grant-operator", "--revoke", str(roles["ops"][0])]) == 0
    with session_scope(get_settings()) as s:
        now = {k.name: k.operator for k in s.scalars(select(ApiKey))}
    assert now == {"ops": False, "alice": True}
    capsys.readouterr()
    assert main(["keys", "list"]) == 0
    assert "operator" in capsys.readouterr().out
    assert main(["keys", "grant-operator", "999"]) == 2
