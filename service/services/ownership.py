"""The rule every per-key object of the service follows: another key's object does not
exist (404, never 403, so that its id tells nothing), except on an operator's dashboard,
which reads every key's jobs and campaigns (``everyone``)."""

from __future__ import annotations

from typing import Protocol, TypeVar

from sqlalchemy.orm import Session

from osdar_platform.models import ApiKey
from service.errors import NotFound


class Owned(Protocol):
    """A row that belongs to one API key (jobs, campaigns, sequences, assets)."""

    @property
    def owner_id(self) -> int: ...


OwnedT = TypeVar("OwnedT", bound=Owned)


def owned_or_404(
    session: Session,
    model: type[OwnedT],
    object_id: str,
    *,
    owner: ApiKey,
    what: str,
    everyone: bool = False,
) -> OwnedT:
    """The ``model`` row ``object_id`` if ``owner`` may read it: NotFound ("``what`` id not
    found") when there is none or it is another key's, unless ``everyone`` (an operator)."""
    row = session.get(model, object_id)
    if row is None or (row.owner_id != owner.id and not everyone):  # others' do not exist
        raise NotFound(f"{what} {object_id} not found")
    return row


__all__ = ["Owned", "owned_or_404"]
