"""Multi-process runs of the command line (``jaxreg basin``, ``jaxreg bop``): the options that
name the processes and the ``jax.distributed`` join they lead to."""

from __future__ import annotations

import argparse


def add_process_options(parser: argparse.ArgumentParser) -> None:
    """Adds ``--coordinator HOST:PORT --num-processes N --process-id I`` to ``parser``."""
    parser.add_argument("--coordinator", help="HOST:PORT of process 0 (multi-process runs)")
    parser.add_argument("--num-processes", type=int, default=1)
    parser.add_argument("--process-id", type=int, default=0)


def join(args) -> None:
    """``jax.distributed.initialize`` for a multi-process run (gloo collectives on CPU);
    nothing without ``--coordinator``.

    Raises:
        ValueError: several processes without a coordinator, or a process id out of range.
    """
    if args.coordinator is None:
        if args.num_processes != 1:
            raise ValueError("--num-processes needs --coordinator HOST:PORT")
        return
    if not 0 <= args.process_id < args.num_processes:
        raise ValueError(f"--process-id must lie in 0 .. {args.num_processes - 1}")
    import jax

    if jax.config.jax_platforms in (None, "", "cpu") or "cpu" in str(jax.config.jax_platforms):
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(args.coordinator, args.num_processes, args.process_id)
