"""Assets uploaded as archives: an OBJ with its MTL and texture (zip, tar.gz) is
accepted and stored as uploaded; unsafe or ambiguous archives are 422 saying why."""

from __future__ import annotations

import pytest

from osdar_platform.models import Asset
from tests.renderer.test_user_mesh import obj_quad_archive
from tests.service.test_service_api import upload_asset


@pytest.mark.parametrize("kind", ["zip", "tar.gz"])
def test_obj_mtl_texture_archive_accepted(api, kind: str) -> None:
    data = obj_quad_archive(kind)
    r = upload_asset(api, data=data, ft=kind)
    assert r.status_code == 201, r.text
    asset = r.json()
    assert asset["file_type"] == kind and asset["faces"] == 2 and asset["size"] == len(data)
    store = api.client.app.state.store
    with api.sessions.begin() as s:
        key = s.get(Asset, asset["id"]).store_key
    assert key.endswith(f".{kind}") and b"".join(store.open_read(key)) == data


def test_unsafe_or_ambiguous_archives_refused(api) -> None:
    outside = obj_quad_archive("zip", mtl_map="../../secret.png")
    r = upload_asset(api, data=outside, ft="zip")
    assert r.status_code == 422 and "not a file in the archive" in r.text
    two = obj_quad_archive("zip", extra={"model/other.ply": b"ply\n"})
    r = upload_asset(api, data=two, ft="zip")
    assert r.status_code == 422 and "exactly one mesh file" in r.text
    r = upload_asset(api, data=b"PK\x03\x04 truncated", ft="zip")
    assert r.status_code == 422 and "archive refused" in r.text
