"""The ``osdar-ar`` command line: the dispatcher.

One module per command group, named after it: :mod:`.synth`, :mod:`.info`, :mod:`.demo`,
:mod:`.serve` (``serve``, ``worker``), :mod:`.prepare`, :mod:`.augment`, :mod:`.campaign`,
:mod:`.evaluate`, :mod:`.bench`, :mod:`.keys` (``keys``, ``migrate``). Each has its
``run(args)`` and imports the library it calls at its top; its arguments
(``add_parser(sub)``) are in the same-named module of :mod:`.arguments`, which imports
nothing but ``argparse``. The parser is built from every group's arguments; only the
chosen command's module is imported, when it runs (:func:`_run`).

Why lazily: what importing each costs, measured on the 2-core development machine
(``/usr/bin/time python -c "import M"``, median of 5 runs, peak RSS; a bare interpreter
is 0.02 s, 10 MB; the seconds move by some 15% with the machine's load, the MB do not)::

    worker.cli (the dispatcher; --help 0.05 s)       0.04 s    12 MB
    worker.cli.info                                  0.45 s    89 MB
    worker.cli.serve    (serve, worker)              0.44 s    67 MB
    worker.cli.keys     (keys, migrate)              0.48 s    63 MB
    worker.cli.synth                                 1.15 s   287 MB
    worker.cli.prepare                               1.50 s   339 MB
    worker.cli.augment                               1.79 s   362 MB
    worker.cli.evaluate                              1.87 s   366 MB
    worker.cli.demo                                  2.10 s   349 MB
    worker.cli.bench                                 2.42 s   388 MB
    all of them                                      3.44 s   448 MB

Imported at the top, every command (``keys list``, ``migrate``, ``--help``) would pay the
last line; and ``worker`` must set its thread caps before numpy is loaded.
"""

from __future__ import annotations

import argparse
import logging
import sys

from worker.cli.arguments import augment as augment_arguments
from worker.cli.arguments import bench as bench_arguments
from worker.cli.arguments import campaign as campaign_arguments
from worker.cli.arguments import demo as demo_arguments
from worker.cli.arguments import evaluate as evaluate_arguments
from worker.cli.arguments import info as info_arguments
from worker.cli.arguments import keys as keys_arguments
from worker.cli.arguments import prepare as prepare_arguments
from worker.cli.arguments import serve as serve_arguments
from worker.cli.arguments import synth as synth_arguments
from worker.cli.errors import CliError

__all__ = ["CliError", "build_parser", "main"]

#: The command groups' arguments, in the order of ``osdar-ar --help``.
ARGUMENTS = (
    synth_arguments,
    info_arguments,
    demo_arguments,
    serve_arguments,
    prepare_arguments,
    augment_arguments,
    campaign_arguments,
    evaluate_arguments,
    bench_arguments,
    keys_arguments,
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="osdar-ar",
        description="Augmented railway perception data in the OSDaR23 layout.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0)
    sub = parser.add_subparsers(dest="command", required=True)
    for arguments in ARGUMENTS:
        arguments.add_parser(sub)
    return parser


def _run(args: argparse.Namespace) -> int:
    """Import the command group's module and run the command."""
    group = args.command_group
    # Only the chosen command's module: the module docstring has the figures.
    if group == "synth":
        from worker.cli import synth  # lazy: 1.2 s, 287 MB RSS (module docstring)

        return synth.run(args)
    if group == "info":
        from worker.cli import info  # lazy: 0.45 s, 89 MB RSS (module docstring)

        return info.run(args)
    if group == "demo":
        from worker.cli import demo  # lazy: 2.1 s, 349 MB RSS (module docstring)

        return demo.run(args)
    if group == "serve":
        from worker.cli import serve  # lazy: 0.44 s, 67 MB RSS (module docstring)

        return serve.run(args)
    if group == "prepare":
        from worker.cli import prepare  # lazy: 1.5 s, 339 MB RSS (module docstring)

        return prepare.run(args)
    if group == "augment":
        from worker.cli import augment  # lazy: 1.8 s, 362 MB RSS (module docstring)

        return augment.run(args)
    if group == "campaign":
        from worker.cli import campaign  # lazy: the augmentation's imports (as augment)

        return campaign.run(args)
    if group == "evaluate":
        from worker.cli import evaluate  # lazy: 1.9 s, 366 MB RSS (module docstring)

        return evaluate.run(args)
    if group == "bench":
        from worker.cli import bench  # lazy: 2.4 s, 388 MB RSS (module docstring)

        return bench.run(args)
    if group == "keys":
        from worker.cli import keys  # lazy: 0.48 s, 63 MB RSS (module docstring)

        return keys.run(args)
    raise AssertionError(f"no command module for the group {group!r}")  # pragma: no cover


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG
        if args.verbose > 1
        else logging.INFO
        if args.verbose
        else logging.WARNING,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    try:
        return int(_run(args) or 0)
    except (CliError, FileNotFoundError) as exc:
        print(f"osdar-ar {args.command}: error: {exc}", file=sys.stderr)  # noqa: T201
        return 2
    except Exception as exc:
        # worker.osdar.errors runs worker/osdar/__init__: 0.50 s, 89 MB RSS, numpy with it,
        # which `osdar-ar worker` must not load before it sets the thread caps. When a
        # SequenceError was raised, the module is loaded already.
        # lazy: 0.50 s, 89 MB RSS and numpy, for every command (above)
        from worker.osdar.errors import SequenceError

        if not isinstance(exc, SequenceError):
            raise
        print(f"osdar-ar {args.command}: error: {exc}", file=sys.stderr)  # noqa: T201
        return 2
