"""Command line: ``streamsvd ingest | info | export | plot | check | dmd``.

Output. A command's result (the JSON summary of ``ingest``, the report of ``info``, the
``wrote ...`` line of ``export`` and ``plot``) is the only thing written to stdout;
progress bars and log messages go to stderr, and ``ingest --quiet`` silences the bar and
the summary. ``streamsvd ingest ... > summary.json`` and ``streamsvd info STORE --json``
therefore give pure JSON. When the reader of stdout has gone (``streamsvd info STORE |
head``), the command ends silently with status 141, as a shell reports a tool that
SIGPIPE ended.

Errors. A user mistake (missing file, locked or foreign store, bad option, an option of
another mode, bad data) prints one line ``streamsvd: error: ...`` in the words of the
command line (its arguments, options and commands, never a Python call) and exits with
status 2; nothing prints a traceback unless ``--debug`` is given. A NaN or infinite entry
met by ``ingest`` after STORE committed snapshots also says that STORE is kept, what it
holds and the command that continues it (``--resume``).

Start-up and exit. At module level the package imports only the standard library and
:mod:`streamsvd.errors`; numpy, zarr, dask, numba and matplotlib are imported by the
command that needs them, so ``streamsvd --help`` answers at once. The executable
(:func:`console`: ``streamsvd`` and ``python -m streamsvd``) leaves without the
interpreter's teardown once nothing is left running (:func:`leave`).

Modules. :mod:`~streamsvd.cli.parsing` (the arguments), :mod:`~streamsvd.cli.ingest`
(``ingest``), :mod:`~streamsvd.cli.reading` (``info``, ``export``, ``plot``,
``check``), :mod:`~streamsvd.cli.dmd` (``dmd``), :mod:`~streamsvd.cli.printing`
(results on stdout) and
:mod:`~streamsvd.cli.wording` (errors in the words of the command line); :func:`main`
runs a command.
"""

from __future__ import annotations

import atexit
import contextlib
import logging
import os
import sys
import threading
import traceback
import warnings
from typing import NoReturn

from streamsvd.cli import dmd, ingest, reading
from streamsvd.cli.parsing import build_parser, locate
from streamsvd.cli.types import CONVERGE
from streamsvd.cli.wording import failed, interrupted
from streamsvd.errors import StreamSVDError

__all__ = ["CONVERGE", "console", "leave", "main"]

#: The exit status after stdout's reader has gone, as a shell reports a process that
#: SIGPIPE ended (128 + 13; 130 after Ctrl-C is 128 + SIGINT).
_BROKEN_PIPE = 141

_COMMANDS = {"ingest": ingest.run, "info": reading.info, "export": reading.export,
             "plot": reading.plot, "check": reading.check, "dmd": dmd.run}


def main(argv: list[str] | None = None) -> int:
    """Run the ``streamsvd`` command.

    Parameters
    ----------
    argv : list of str, optional
        The arguments after the command name; ``sys.argv[1:]`` when omitted.

    Returns
    -------
    int
        The exit status: 0 on success (and after ``--help``), 2 after a user mistake
        (reported on one line of stderr as ``streamsvd: error: ...``), 130 after Ctrl-C
        (one line saying what the store holds and the command that continues), 141,
        silently, when the reader of stdout has gone (``streamsvd info STORE | head``).
    """
    argv = sys.argv[1:] if argv is None else [str(a) for a in argv]
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # --help, --version (0) or a usage error (2), already printed
        return int(exc.code or 0)
    logging.basicConfig(level=logging.WARNING, format="streamsvd: %(message)s")
    if not args.debug:
        # dask.distributed sets its loggers to INFO from its config when first imported
        # (here, lazily); the config can be given by environment, which workers inherit
        os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "warning")
    try:
        locate(args)
        status = int(_COMMANDS[args.command](args))
        sys.stdout.flush()  # a reader gone (`streamsvd info STORE | head`) shows here
        return status
    except BrokenPipeError:  # stdout is the one pipe the command writes to
        _discard_stdout()
        return _BROKEN_PIPE
    except KeyboardInterrupt as exc:
        # an interrupt inside a commit can leave a coroutine of zarr's created but never
        # run (the store keeps its last commit): released here, without its warning
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", "coroutine .* was never awaited", RuntimeWarning)
            traceback.clear_frames(exc.__traceback__)
        print(interrupted(args, argv), file=sys.stderr)
        return 130
    except (StreamSVDError, OSError, ValueError) as err:
        if args.debug:
            raise
        print(f"streamsvd: error: {failed(err, args, argv)}", file=sys.stderr)
        return 2


def console() -> NoReturn:
    """Run the ``streamsvd`` executable: :func:`main` on ``sys.argv``, then :func:`leave`."""
    leave(main())


def leave(status: int) -> NoReturn:
    """End the process with ``status``, without tearing the interpreter down.

    With scipy, zarr and numba loaded the interpreter's teardown takes about 0.15 s
    (``streamsvd ingest`` of ``bench/studies/tight-targets.md``), after every file the
    command wrote was synced and closed. What an exit must still do is done here: the
    ``atexit`` handlers run (logging's, dask's) and stdout and stderr are flushed. While
    a thread other than a daemon is still running, the exit is the interpreter's own,
    which waits for it.
    """
    alive = [t for t in threading.enumerate()
             if t is not threading.main_thread() and not t.daemon and t.is_alive()]
    if alive:
        sys.exit(status)
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):  # a reader gone: nothing to tell
            stream.flush()
    os._exit(status)


def _discard_stdout() -> None:
    """Send what is left of stdout to the null device: its reader has gone.

    The interpreter flushes stdout once more at exit, which would report the closed
    pipe again; a stdout without a file descriptor (a test's capture) is left as it is.
    """
    with contextlib.suppress(AttributeError, OSError, ValueError):
        devnull = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, sys.stdout.fileno())
        finally:
            os.close(devnull)
