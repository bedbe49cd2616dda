"""Fault campaign against the basis store: kills, interrupts, zombies, readers, full disks, damage.

Each scenario prints one line ``PASS|FAIL  kind  where  detail``; the script ends with a
summary line and exits 1 if any scenario failed. Scenarios, on a local directory and on
an S3 server on localhost (moto, started by the script, ``streamsvd.testing.s3server``):

* ``kill``: ``streamsvd ingest`` (a subprocess) gets SIGKILL or SIGINT at a random instant,
  or at each named step of a commit (``streamsvd.store.CRASH_POINTS``, by a wrapper that
  signals itself there). After each one the store must verify (``check_store``) and hold
  a whole commit; the chain of runs ends with ``--resume`` to completion, which must
  equal an uninterrupted run bit for bit.
* ``zombie``: a writer is paused (SIGSTOP) at each named step or at a random instant; on
  S3 (leases of a few seconds) another ``--resume`` takes the lease over and finishes the
  ingestion; then the paused writer is woken (SIGCONT). The store must verify and equal
  the uninterrupted run; locally the second writer must be refused while the first is
  paused, and the first must finish after SIGCONT.
* ``readers``: three threads read the store in a loop during a whole ingestion; every
  read must succeed and be consistent.
* ``enospc``: ``os.write`` fails with ENOSPC once a byte budget is spent, at budgets
  spread over the creation and the first commits (in this process): a failed creation
  leaves nothing and creating again works; a failed commit leaves the last one intact.
* ``damage``: each corruption (a flipped byte, a missing chunk, edited attributes, a
  garbled, missing or rolled-back pointer, an edited root ``n`` or ``dtype``): ``check``
  exits 2, ``ingest --resume`` exits 2 and changes no file.

The campaign stops starting new scenarios once ``--seconds`` have passed; ``--only``
runs some groups of scenarios. With ``--out DIR`` it also writes ``fault_campaign.json``
there: every scenario's line and the count of scenarios and failures per kind and place.
"""

from __future__ import annotations

import argparse
import errno
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from _common import Run, out_dir

from streamsvd.cli import main as cli
from streamsvd.engine.record import HISTORY_FIELDS
from streamsvd.parallel.cluster import check_store
from streamsvd.storage import open_storage
from streamsvd.store import CRASH_POINTS, POINTER_NAME, open_store
from streamsvd.testing.damage import GENERATION_DAMAGE, damage_generation

# a writer run as `python -c WRAPPER <point> <signal> <nth> <lease seconds> -- <cli args>`
WRAPPER = r"""
import os, signal, sys
point, sig, nth, lease = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
argv = sys.argv[sys.argv.index("--") + 1:]
import streamsvd.storage.lease as locks, streamsvd.storage as storage
import streamsvd.store.fence as fence
if lease > 0:
    storage.ObjectStorage.lock = lambda self, key: locks.Lease(self, key, seconds=lease)
seen = []
def crash(name):
    if name == point:
        seen.append(name)
        if len(seen) == nth:
            os.kill(os.getpid(), getattr(signal, sig))
fence.crash_point = crash
from streamsvd.cli import main
sys.exit(main(argv))
"""

GROUPS = ("kills-local", "zombies-local", "readers-local", "enospc", "damage", "kills-s3",
          "zombies-s3", "readers-s3")
SEED = 2026
N, M, BLOCK = 120, 600, 8


class Campaign:
    """Runs the scenarios and prints one line for each."""

    def __init__(self, root: Path, seconds: float, s3: Any) -> None:
        self.root = root
        self.deadline = time.monotonic() + seconds
        self.s3 = s3
        self.rng = random.Random(SEED)
        self.results: list[tuple[str, str, bool, str]] = []
        self.source = root / "a.npy"
        A = np.random.default_rng(SEED).standard_normal((N, 30)) @ (
            np.random.default_rng(SEED + 1).standard_normal((30, M)))
        np.save(self.source, A)
        self.reference = root / "reference.zarr"
        assert cli(self._args(self.reference)) == 0

    # ------------------------------------------------------------------ helpers

    def left(self) -> bool:
        return time.monotonic() < self.deadline

    def report(self, kind: str, where: str, ok: bool, detail: str) -> None:
        self.results.append((kind, where, ok, detail))
        print(f"{'PASS' if ok else 'FAIL'}  {kind:8s} {where:6s} {detail}", flush=True)

    def _args(self, store: Any, *extra: str) -> list[str]:
        return ["ingest", str(self.source), str(store), "--block", str(BLOCK), "--quiet",
                "--max-rank", "20", "--final-sweeps", "none", *extra]

    def spawn(self, store: Any, *, point: str = "-", sig: str = "SIGKILL", nth: int = 1,
              lease: float = 0.0, resume: bool = True) -> subprocess.Popen[bytes]:
        args = self._args(store, *(["--resume"] if resume else []))
        return subprocess.Popen(
            [sys.executable, "-c", WRAPPER, point, sig, str(nth), str(lease), "--", *args],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
        )

    def verified(self, store: Any) -> tuple[bool, str]:
        """Whether the store verifies (or was never created), and its last commit."""
        storage = open_storage(store)
        if POINTER_NAME not in storage.list():
            return storage.list() in ([], ["writer.lock"], ["writer.lease"]), "no store"
        report = check_store(storage)
        if not report.healthy:
            return False, report.problems[0]
        with open_store(store) as st:
            state = st.read()
        return True, f"generation {state.generation}, offset {state.attrs.get('source_offset')}"

    def same_as_reference(self, store: Any) -> tuple[bool, str]:
        with open_store(self.reference) as a, open_store(store) as b:
            sa, sb = a.read(), b.read()
        seconds = HISTORY_FIELDS.index("seconds")
        for name, x in sa.arrays.items():
            y = sb.arrays.get(name)
            if name == "history" and y is not None:
                x, y = x.copy(), y.copy()
                x[:, seconds] = y[:, seconds] = 0.0
            if y is None or x.shape != y.shape or not np.array_equal(x, y):
                return False, f"array {name} differs from the uninterrupted run"
        return True, "bit-identical to the uninterrupted run"

    def finish(self, store: Any, where: str, lease: float = 0.0) -> None:
        proc = self.spawn(store, lease=lease)
        err = proc.communicate(timeout=600)[1].decode()
        ok, detail = (False, f"--resume exited {proc.returncode}: {err.strip()[-300:]}")
        if proc.returncode == 0:
            ok, detail = self.same_as_reference(store)
        self.report("resume", where, ok, detail)

    # ----------------------------------------------------------------- scenarios

    def kill_chain(self, store: Any, where: str, plan: list[tuple[str, str, int]]) -> None:
        """Run the writer again and again, each run stopped as ``plan`` says, then finish."""
        for point, sig, nth in plan:
            if not self.left():
                break
            proc = self.spawn(store, point=point, sig=sig, nth=nth)
            if point == "-":  # a random instant, during start-up (1 in 4) or the ingestion
                if self.rng.random() < 0.75:
                    _wait_for_commit(store, proc)
                time.sleep(self.rng.uniform(0.0, 2.0))
                proc.send_signal(getattr(signal, sig))
            try:
                err = proc.communicate(timeout=600)[1].decode()
            except subprocess.TimeoutExpired:
                proc.kill()
                err = proc.communicate()[1].decode()
            ok, detail = self.verified(store)
            code = proc.returncode
            expected = code in (0, 130, -signal.SIGKILL, -signal.SIGINT)
            if not expected:
                ok, detail = False, f"exit {code}: {err.strip()[-300:]}"
            at = "random" if point == "-" else f"{point}#{nth}"
            self.report("kill", where, ok, f"{sig} at {at}: exit {code}; {detail}")
        self.finish(store, where)

    def kills(self, where: str, store_of: Callable[[int], Any], randoms: int) -> None:
        plans = [("-", self.rng.choice(["SIGKILL", "SIGINT"]), 1) for _ in range(randoms)]
        plans += [(p, s, self.rng.randint(1, 8)) for p in CRASH_POINTS
                  for s in ("SIGKILL", "SIGINT")]
        self.rng.shuffle(plans)
        for i in range(0, len(plans), 6):
            if self.left():
                self.kill_chain(store_of(i), where, plans[i : i + 6])

    def zombie(self, store: Any, where: str, point: str) -> None:
        lease = 3.0 if where == "s3" else 0.0
        first = self.spawn(store, point=point, sig="SIGSTOP", nth=self.rng.randint(2, 12),
                           lease=lease)
        if point == "-":
            time.sleep(self.rng.uniform(1.0, 4.0))
            first.send_signal(signal.SIGSTOP)
        stopped = _wait_stopped(first, timeout=120)
        if not stopped:  # it finished (or failed) before reaching the point
            first.communicate(timeout=600)
            self.report("zombie", where, first.returncode == 0,
                        f"at {point}: the writer ended before pausing (exit {first.returncode})")
            return
        if where == "s3":
            time.sleep(lease + 1.5)  # its lease expires
            second = self.spawn(store, lease=lease)
            err2 = second.communicate(timeout=600)[1].decode()
            first.send_signal(signal.SIGCONT)
            err1 = first.communicate(timeout=600)[1].decode()
            ok, detail = self.verified(store)
            if ok and second.returncode == 0:
                ok, detail = self.same_as_reference(store)
            elif second.returncode != 0:
                ok, detail = False, f"the taker exited {second.returncode}: {err2[-300:]}"
            self.report("zombie", where, ok, f"paused at {point}, woken after a takeover: "
                        f"zombie exit {first.returncode} ({_last_line(err1)}); {detail}")
        else:
            held = _holds_lock(Path(store), first.pid)  # paused before it took the lock?
            second = self.spawn(store)
            err2 = second.communicate(timeout=600)[1].decode()
            refused = second.returncode == 2 and "locked by another writer" in err2
            first.send_signal(signal.SIGCONT)
            err1 = first.communicate(timeout=600)[1].decode()
            ok, detail = self.same_as_reference(store)
            if held:  # the second is refused while the first is paused, which then ends
                ok = ok and refused and first.returncode == 0
                what = f"second writer refused ({refused}), first exit {first.returncode}"
            else:  # paused before locking: the second runs, the first then finds it
                ok = ok and second.returncode == 0 and first.returncode in (0, 2)
                what = (f"paused before it took the lock: second exit {second.returncode}, "
                        f"first exit {first.returncode} ({_last_line(err1)})")
            self.report("zombie", where, ok, f"paused at {point}: {what}; {detail}")

    def readers(self, store: Any, where: str) -> None:
        proc = self.spawn(store, resume=False)
        storage = open_storage(store)
        while POINTER_NAME not in storage.list() and proc.poll() is None:
            time.sleep(0.05)
        reads, failures = [0], []
        done = threading.Event()

        def loop() -> None:
            while not done.is_set():
                try:
                    with open_store(store) as st:
                        state = st.read()
                    if state.arrays and state.attrs["n_seen"] != state.attrs["source_offset"]:
                        failures.append(f"inconsistent generation {state.generation}")
                    reads[0] += 1
                except Exception as exc:  # noqa: BLE001 - every failure is reported
                    failures.append(f"{type(exc).__name__}: {exc}")
        threads = [threading.Thread(target=loop) for _ in range(3)]
        for t in threads:
            t.start()
        proc.communicate(timeout=900)
        done.set()
        for t in threads:
            t.join()
        ok, detail = self.same_as_reference(store) if proc.returncode == 0 else (False, "")
        self.report("readers", where, ok and not failures,
                    f"{reads[0]} reads by 3 threads during the ingestion, {len(failures)} "
                    f"failed{': ' + failures[0][:200] if failures else ''}; {detail}")

    def enospc(self, budgets: int) -> None:
        from streamsvd.store import BasisStore

        def run(path: Path) -> None:
            with BasisStore.create(path, n=50, inner_fingerprint="f" * 64) as s:
                for k in (1, 2):
                    s.commit({"U": np.full((50, 3), float(k))}, {"k": k})
        real = os.write
        total = [0]

        def counting(fd: int, data: Any) -> int:
            total[0] += len(data)
            return real(fd, data)
        os.write = counting
        try:
            run(self.root / "enospc-probe.zarr")
        finally:
            os.write = real
        for i, budget in enumerate(np.linspace(0, total[0] - 1, budgets).astype(int)):
            path = self.root / f"enospc{i}.zarr"
            left = [int(budget)]

            def full(fd: int, data: Any, left: list[int] = left) -> int:
                if left[0] <= 0:
                    raise OSError(errno.ENOSPC, "No space left on device")
                n = real(fd, bytes(data)[: left[0]])
                left[0] -= n
                return n
            os.write = full
            try:
                run(path)
                outcome = "no failure"
            except OSError as exc:
                outcome = str(exc)
            finally:
                os.write = real
            if "creating the store failed" in outcome:
                ok = not path.exists()
                run(path)  # space freed: creating works
                detail = "creation failed, nothing left, created again"
            else:
                ok, detail = self.verified(path)
                with open_store(path, "a") as s:
                    s.commit({"U": np.zeros((50, 3))}, {"k": 9})
            ok = ok and check_store(open_storage(path)).healthy
            self.report("enospc", "local", ok, f"budget {budget} of {total[0]} bytes: "
                        f"{detail}; {outcome[:120]}")

    def damage(self) -> None:
        for kind in ("flip", "missing-chunk", "attrs", "pointer-garbled", "pointer-missing",
                     "pointer-rolled-back", "root-n", "root-dtype"):
            store = self.root / f"damage-{kind}.zarr"
            shutil.copytree(self.reference, store)
            _damage(store, kind)
            before = _tree(store)
            with _quiet():
                checked = cli(["check", str(store)])
                resumed = cli(self._args(store, "--resume"))
            ok = checked == 2 and resumed == 2 and _tree(store) == before
            self.report("damage", "local", ok, f"{kind}: check exit {checked}, --resume exit "
                        f"{resumed}, files unchanged: {_tree(store) == before}")


def _damage(store: Path, kind: str) -> None:
    pointer = json.loads((store / POINTER_NAME).read_text())
    gen = store / "generations" / f"g{pointer['generation']:08d}"
    if kind in GENERATION_DAMAGE:
        damage_generation(gen, kind)
    elif kind == "pointer-garbled":
        (store / POINTER_NAME).write_text("{not json")
    elif kind == "pointer-missing":
        (store / POINTER_NAME).unlink()
    elif kind == "pointer-rolled-back":
        previous = store / "generations" / f"g{pointer['previous']:08d}" / "committed.json"
        (store / POINTER_NAME).write_bytes(previous.read_bytes())
    else:
        doc = json.loads((store / "zarr.json").read_text())
        field, value = ("n", N + 1) if kind == "root-n" else ("dtype", "float32")
        doc["attributes"][field] = value
        (store / "zarr.json").write_text(json.dumps(doc))


def _tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*")
            if p.is_file() and p.name != "writer.lock"}


class _quiet:
    """Silence the CLI's stdout and stderr (its messages are checked by exit status)."""

    def __enter__(self) -> None:
        self.saved = sys.stdout, sys.stderr
        sys.stdout = sys.stderr = open(os.devnull, "w")  # noqa: SIM115

    def __exit__(self, *exc: object) -> None:
        sys.stdout.close()
        sys.stdout, sys.stderr = self.saved


def _wait_for_commit(store: Any, proc: subprocess.Popen[bytes], timeout: float = 120) -> None:
    """Wait until ``proc`` commits (the pointer changes) or ends."""
    storage = open_storage(store)
    seen = storage.get_tagged(POINTER_NAME)
    end = time.monotonic() + timeout
    while time.monotonic() < end and proc.poll() is None:
        now = storage.get_tagged(POINTER_NAME)
        if now is not None and (seen is None or now[1] != seen[1]):
            return
        time.sleep(0.05)


def _wait_stopped(proc: subprocess.Popen[bytes], timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if proc.poll() is not None:
            return False
        try:
            state = Path(f"/proc/{proc.pid}/stat").read_text().split()[2]
        except OSError:
            return False
        if state == "T":
            return True
        time.sleep(0.05)
    return False


def _holds_lock(store: Path, pid: int) -> bool:
    """Whether process ``pid`` holds the writer lock of the local store ``store``."""
    try:
        return json.loads((store / "writer.lock").read_text()).get("pid") == pid
    except (OSError, ValueError):
        return False


def _last_line(text: str) -> str:
    lines = [line for line in text.strip().splitlines() if line.strip()]
    return lines[-1][:160] if lines else "no message"


def main(argv: Sequence[str] | None = None) -> int:
    record = Run("fault_campaign", argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seconds", type=float, default=1500.0,
                   help="start no new scenario after this many seconds (default 1500)")
    p.add_argument("--local-kills", type=int, default=24,
                   help="random kills on a local directory, besides the 12 at named steps")
    p.add_argument("--s3-kills", type=int, default=6,
                   help="random kills on S3, besides the 12 at named steps (default 6)")
    p.add_argument("--no-s3", action="store_true", help="skip the S3 scenarios")
    p.add_argument("--only", default=",".join(GROUPS),
                   help=f"comma-separated groups to run (default: all, {','.join(GROUPS)})")
    p.add_argument("--out", default=None,
                   help="directory for fault_campaign.json (default: no JSON is written)")
    args = p.parse_args(argv)
    only = set(args.only.split(","))
    if only - set(GROUPS):
        p.error(f"--only takes groups among {', '.join(GROUPS)}; got {args.only!r}")
    started = time.monotonic()
    print(f"load before: {os.getloadavg()}", flush=True)
    root = Path(tempfile.mkdtemp(prefix="streamsvd-faults-"))
    server = None
    try:
        if not args.no_s3:
            from streamsvd.testing.s3server import start

            server = start()
            os.environ.update(server.environment())
            import s3fs

            s3fs.S3FileSystem().mkdir("campaign")
        campaign = Campaign(root, args.seconds, server)
        if "kills-local" in only:
            campaign.kills("local", lambda i: root / f"kill{i}.zarr", args.local_kills)
        for point in ("-", *CRASH_POINTS[:3]) if "zombies-local" in only else ():
            if campaign.left():
                campaign.zombie(root / f"zombie-{point}.zarr", "local", point)
        if "readers-local" in only:
            campaign.readers(root / "readers.zarr", "local")
        if "enospc" in only:
            campaign.enospc(30)
        if "damage" in only:
            campaign.damage()
        if server is not None:
            if "kills-s3" in only:
                campaign.kills("s3", lambda i: f"s3://campaign/kill{i}.zarr", args.s3_kills)
            for point in ("-", *CRASH_POINTS) if "zombies-s3" in only else ():
                if campaign.left():
                    campaign.zombie(f"s3://campaign/zombie-{point}.zarr", "s3", point)
            if "readers-s3" in only and campaign.left():
                campaign.readers("s3://campaign/readers.zarr", "s3")
    finally:
        if server is not None:
            server.stop()
        shutil.rmtree(root, ignore_errors=True)
    results = campaign.results
    failed = sum(not ok for _, _, ok, _ in results)
    kinds: dict[str, int] = {}
    failures: dict[str, int] = {}
    for kind, where, ok, _ in results:
        kinds[f"{kind}/{where}"] = kinds.get(f"{kind}/{where}", 0) + 1
        failures[f"{kind}/{where}"] = failures.get(f"{kind}/{where}", 0) + (not ok)
    print(f"{len(results)} scenarios, {failed} failed, in {time.monotonic() - started:.0f} s; "
          f"{kinds}; load after: {os.getloadavg()}", flush=True)
    if args.out is not None:
        record.write(out_dir(args.out) / "fault_campaign.json", {
            "groups": sorted(only), "s3": server is not None, "seconds_limit": args.seconds,
            "seconds": time.monotonic() - started, "failed": failed,
            "scenarios": [{"kind": kind, "where": where, "passed": ok, "detail": detail}
                          for kind, where, ok, detail in results],
            "counts": [{"kind": key.split("/")[0], "where": key.split("/")[1], "count": count,
                        "failed": failures[key]} for key, count in kinds.items()],
        })
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
