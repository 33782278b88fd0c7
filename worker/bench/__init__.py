"""``osdar-ar bench``: speed against error (../shared/design/BENCHMARK.md).

- :mod:`.paper`: the synthetic counterparts of the paper's three sequences, every strategy,
  the paper's table layout with the paper's numbers beside ours (OSDAR23.md);
- :mod:`.pareto`: configurations (strategy x knobs) -> seconds and error, Pareto front;
- :mod:`.floor`: the augmentation job against its I/O floor;
- :mod:`.hard_cases`: the 12 hard cases, each with its bound;
- :mod:`.run`: the command (prints the tables, writes JSON / CSV / plots).
"""
