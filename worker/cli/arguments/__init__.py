"""The arguments of every ``osdar-ar`` command group: one module per group, each with its
``add_parser(sub)``. They import only ``argparse`` and the standard library, so building
the whole parser (``osdar-ar --help``) stays cheap; the groups' commands are in the
same-named modules of :mod:`worker.cli`."""
