"""A job's frames dealt into chunks: as few as the chunk size allows, alike in length and
in where along the sequence their frames lie."""

from __future__ import annotations

import pytest

from worker.orchestration.runner import split_frames


@pytest.mark.parametrize("n_frames", [1, 2, 7, 24, 25, 26, 40, 49, 50, 51, 100, 101])
@pytest.mark.parametrize("per_chunk", [1, 2, 7, 25])
def test_every_frame_once_in_few_even_chunks(n_frames: int, per_chunk: int) -> None:
    frames = list(range(10, 10 + 2 * n_frames, 2))  # frame numbers need not be 0..n-1
    chunks = split_frames(frames, per_chunk)
    assert len(chunks) == -(-n_frames // per_chunk)  # no more chunks than the size needs
    assert sorted(f for c in chunks for f in c) == frames
    assert all(c == sorted(c) and 0 < len(c) <= per_chunk for c in chunks)
    assert max(map(len, chunks)) - min(map(len, chunks)) <= 1
    assert chunks[0][0] == frames[0]  # the plan's decoded first frame is the first chunk's


def test_chunks_side_by_side_share_the_costly_frames() -> None:
    """The object grows as the train nears it: a frame's cost rises along the sequence.
    Dealt in turn, the two chunks of 40 frames cost within one frame's cost of each other;
    in runs (25 + 15 frames) they differed by more than the costliest frame."""
    frames = list(range(40))
    cost = {f: 1.0 + f / 10 for f in frames}
    a, b = (sum(cost[f] for f in c) for c in split_frames(frames, 25))
    assert abs(a - b) <= max(cost.values())
    runs = [sum(cost[f] for f in frames[:25]), sum(cost[f] for f in frames[25:])]
    assert abs(runs[0] - runs[1]) > 1.5 * max(cost.values())
