"""Run the benchmark suite, from the repository's root.

    python -m bench --list              the studies' scripts, one line each
    python -m bench NAME [OPTIONS]      run one script (its options: python -m bench NAME -h)
    python -m bench pages [--out DIR]   render the benchmark pages from bench/results

NAME is a script of ``bench/`` (``fig1_pair_dynamics``; ``.py`` and ``-`` for ``_`` are
accepted) or a study whose page has one script (``dask``). A run writes its figures and
its JSON, in the suite's envelope, to ``--out`` (default ``bench/results/``), exactly as
``python bench/NAME.py`` does.
"""

from __future__ import annotations

import ast
import importlib
import sys
from collections.abc import Sequence
from pathlib import Path

BENCH_DIR = Path(__file__).resolve().parent
if str(BENCH_DIR) not in sys.path:
    sys.path.insert(0, str(BENCH_DIR))

from _suite import STUDIES, scripts  # noqa: E402


def summary(script: str) -> str:
    """The first line of a script's docstring, read without importing the script."""
    doc = ast.get_docstring(ast.parse((BENCH_DIR / f"{script}.py").read_text()))
    return (doc or "").strip().splitlines()[0] if doc else ""


def listing() -> str:
    """One line per script: its name, its study's page and what it measures."""
    found = scripts()
    width = max(map(len, found))
    return "\n".join(f"{script:<{width}}  [{study.name}] {summary(script)}"
                     for script, study in found.items())


def resolve(name: str) -> str | None:
    """The script that ``name`` designates, or None."""
    found = scripts()
    stem = name.removesuffix(".py")
    for candidate in (stem, stem.replace("-", "_")):
        if candidate in found:
            return candidate
    study = next((s for s in STUDIES if s.name == stem), None)
    if study is not None and len(study.scripts) == 1:
        return study.scripts[0]
    return None


def run(script: str, argv: Sequence[str]) -> int:
    """Run ``script``'s ``main(argv)``; its exit status (0 unless it returns one)."""
    module = importlib.import_module(script)
    sys.argv = [f"python -m bench {script}", *argv]  # the program name argparse shows
    result = module.main(list(argv))
    return result if isinstance(result, int) else 0


def main(argv: Sequence[str] | None = None) -> int:
    """The command line: ``--list``, ``pages [--out DIR]`` or ``NAME [OPTIONS]``."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help"):
        print(__doc__.strip() + "\n\nScripts:\n" + listing())
        return 0
    if args[0] == "--list":
        print(listing())
        return 0
    if args[0] == "pages":
        from _pages import main as pages

        return pages(args[1:])
    script = resolve(args[0])
    if script is None:
        study = next((s for s in STUDIES if s.name == args[0]), None)
        hint = (f"the study {study.name!r} has several scripts: {', '.join(study.scripts)}"
                if study else "python -m bench --list names them")
        print(f"python -m bench: no study script {args[0]!r}; {hint}", file=sys.stderr)
        return 2
    return run(script, args[1:])


if __name__ == "__main__":
    sys.exit(main())
