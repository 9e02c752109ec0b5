"""``warpskin batch``: many bakes (characters x clips) as one batch on this machine, each job in
its own process, resumable and fault tolerant.

A batch is a list of jobs, each one ``warpskin simulate|skin|pop`` command line: from a JOBS
file (TOML, ``[[job]]`` tables) or from rig files with ``--clips all``. Every job runs the same
code as its single command, in a process of its own (``python -m warpskin ...``), so a crash
takes only that job, and writes the same file, atomically as every command does.

OUTDIR holds the bakes, ``manifest.json`` (per job: its inputs' key, exit code, message,
timing, attempts and output), ``index.md`` (the batch at a glance) and ``logs/`` (each job's
standard output and error). A job whose manifest entry has the same key (the input files'
SHA-256, the command line, the warpskin version) and whose output exists is not run again; a
job whose process dies (a signal, the out-of-memory killer) is run again up to ``retries``
times; a job that fails (exit 2: bad input, 3: the run failed) is recorded and the batch goes
on.

Exit codes of :func:`run_batch`'s command: 0 every job succeeded, 3 some failed (listed), 2 a bad
JOBS file or option (nothing run).
"""

from __future__ import annotations

import argparse
import contextlib
import glob
import hashlib
import io
import json
import math
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

from .parser import build_parser
from .errors import InputError
from .scene import list_scenes, resolve_scene
from .settings import add_option, setting
from .thumbnail import write_thumbnail

try:
    import tomllib
except ModuleNotFoundError:  # Python < 3.11
    import tomli as tomllib

__all__ = ["BatchError", "Job", "BatchResult", "read_jobs", "jobs_for_rigs", "run_batch", "COMMANDS"]

COMMANDS = ("simulate", "skin", "pop")
"""The commands a job may run."""
_JOB_KEYS = {"rig", "command", "clip", "frames", "output", "args"}
_MANIFEST = "manifest.json"
_RETRYABLE_EXITS = {128 + signal.SIGTERM, 128 + signal.SIGHUP}  # the command's own signal exits
# A job's process: the installed warpskin's command line. Not `python -m warpskin`, which puts
# the working folder first on the module path, where a source checkout (warpskin/ without the
# kernels and scenes it is installed with) would shadow the package; relative paths in a job's
# args still mean what they mean on the batch's own command line.
_BOOT = "import sys; sys.path.pop(0); from warpskin.cli import main; sys.exit(main(sys.argv[1:]))"


class BatchError(InputError):
    """A bad JOBS file or batch option: one line naming the file, the job and the key."""


@dataclass
class Job:
    """One bake of a batch.

    Attributes:
        id: Its output path relative to OUTDIR (POSIX separators): unique in the batch.
        rig: A rig file (absolute path), a TOML scene path or a shipped scene name.
        command: ``simulate``, ``skin`` or ``pop``.
        clip: The rig's clip, or ``None`` (the rig's or scene's own).
        frames: ``"A:B"`` or ``None`` (every frame).
        args: The command's own options, as on its command line.
        output: The bake [absolute path].
    """

    id: str
    rig: str
    command: str
    clip: str | None
    frames: str | None
    args: list[str]
    output: Path

    def argv(self) -> list[str]:
        """The job's command line: ``warpskin COMMAND ...`` run by this Python (:data:`_BOOT`)."""
        out = [sys.executable, "-c", _BOOT, self.command, self.rig, "-o", str(self.output)]
        if self.clip is not None:
            out += ["--clip", self.clip]
        if self.frames is not None:
            out += ["--frames", self.frames]
        return out + list(self.args) + ["--quiet", "--json"]

    def key(self, version: str) -> str:
        """SHA-256 of what the bake depends on: the input files' contents, the command line
        (less the interpreter) and the warpskin version."""
        h = hashlib.sha256()
        h.update(json.dumps([version, self.command, self.rig, self.clip, self.frames, self.args]).encode())
        for path in _input_files(self.rig):
            h.update(str(path).encode())
            h.update(_file_hash(path).encode())
        return h.hexdigest()


@dataclass
class BatchResult:
    """What :func:`run_batch` did.

    Attributes:
        entries: The manifest's entry of every job, by job id.
        ran: Ids of the jobs run this time (retries counted once).
        skipped: Ids of the jobs already done (manifest key matched, output present).
        failed: Ids of the jobs that failed (their entries hold the exit code and message).
        seconds: Wall time of the batch [s].
    """

    entries: dict[str, dict] = field(default_factory=dict)
    ran: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def exit_code(self) -> int:
        return 3 if self.failed else 0


# ------------------------------------------------------------------------------ the jobs
def _file_hash(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _input_files(rig: str) -> list[Path]:
    """The files a job's rig reads (its file; a scene's TOML and the rig file it names)."""
    try:
        paths = resolve_scene(rig).input_paths()
    except InputError:
        paths = [Path(rig)]
    return [p for p in paths if p is not None and Path(p).is_file()]


def _check_rig(rig: str, where: str) -> None:
    """A rig that exists: a file, or a shipped scene name."""
    names = [s["name"] for s in list_scenes()]
    if Path(rig).is_file() or rig in names:
        return
    raise BatchError(f"{where}: rig {rig!r} is neither a file nor a shipped scene ({', '.join(names)})")


def _check_args(command: str, rig: str, args: list[str], where: str) -> None:
    """Parse the job's command line as the command would, so that a bad option fails the batch
    before anything runs (argparse's own message, its error line)."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        try:
            build_parser().parse_args([command, rig, "-o", "x.usdc", *args])
        except SystemExit:
            lines = [ln for ln in err.getvalue().strip().splitlines() if ": error: " in ln]
            last = (lines or err.getvalue().strip().splitlines() or ["bad arguments"])[-1]
            raise BatchError(f"{where}: args: {re.sub(r'^warpskin( [a-z]+)?: error: ', '', last)}") from None
    for flag, key in (("-o", "output"), ("--output", "output"), ("--clip", "clip"), ("--frames", "frames"),
                      ("--json", None), ("--quiet", None)):
        if flag in args:
            use = f" (use the job's {key} key)" if key else ""
            raise BatchError(f"{where}: args: {flag} is the batch's to set{use}")


def _clips_of(rig: str) -> list[str | None]:
    """Every clip of a rig (``[None]`` for a rig without any, its rest pose, and for a rig that
    does not load: its one job fails when run, with the command's own message)."""
    import warnings


    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            clips = list(resolve_scene(rig).rig().clips)
    except InputError:
        return [None]
    return clips or [None]


def _stem(rig: str) -> str:
    return Path(rig).stem if (Path(rig).suffix or os.sep in rig) else rig


def _output_of(value, rig: str, clip: str | None, outdir: Path, where: str, stem: str | None = None) -> tuple[str, Path]:
    safe = re.sub(r"[^A-Za-z0-9._-]+", "_", clip).strip("._") if clip else ""
    rel = value if value is not None else f"{stem or _stem(rig)}/{safe or 'default'}.usdc"
    if not isinstance(rel, str) or not rel:
        raise BatchError(f"{where}: output must be a path relative to OUTDIR, got {value!r}")
    pure = PurePosixPath(rel.replace(os.sep, "/"))
    if pure.is_absolute() or ".." in pure.parts:
        raise BatchError(f"{where}: output {rel!r} must stay inside OUTDIR (a relative path without '..')")
    if pure.suffix.lower() not in (".usdc", ".usda", ".usd"):
        raise BatchError(f"{where}: output {rel!r} must end in .usdc, .usda or .usd")
    return str(pure), outdir / pure


def _make_jobs(specs: list[tuple[dict, str]], outdir: Path) -> list[Job]:
    """Jobs from ``[(table, where)]``: checked, clips expanded, outputs unique."""
    jobs: list[Job] = []
    seen: dict[str, str] = {}
    # rigs of one name (CesiumMan.glb, CesiumMan.usdz) keep their kind in their folder's name
    rigs_of: dict[str, set] = {}
    for spec, _ in specs:
        if isinstance(spec.get("rig"), str):
            rigs_of.setdefault(_stem(spec["rig"]), set()).add(spec["rig"])
    clash = {stem for stem, rigs in rigs_of.items() if len(rigs) > 1}
    for spec, where in specs:
        unknown = sorted(set(spec) - _JOB_KEYS)
        if unknown:
            raise BatchError(f"{where}: unknown key(s) {unknown}; known: {sorted(_JOB_KEYS)}")
        rig = spec.get("rig")
        if not isinstance(rig, str) or not rig:
            raise BatchError(f"{where}: rig must be a rig file, a TOML scene or a shipped scene name")
        _check_rig(rig, where)
        command = spec.get("command", "simulate")
        if command not in COMMANDS:
            raise BatchError(f"{where}: command must be one of {', '.join(COMMANDS)}, got {command!r}")
        args = spec.get("args", [])
        if isinstance(args, str):
            args = shlex.split(args)
        if not isinstance(args, list) or not all(isinstance(a, str) for a in args):
            raise BatchError(f"{where}: args must be a list of strings or one string, got {args!r}")
        frames = spec.get("frames")
        if frames is not None and not (isinstance(frames, str) and len(frames.split(":")) == 2
                                       and all(p.strip().lstrip("-").isdigit() for p in frames.split(":"))):
            raise BatchError(f"{where}: frames must be \"A:B\" (inclusive), got {frames!r}")
        clip = spec.get("clip")
        if clip is not None and not isinstance(clip, str):
            raise BatchError(f"{where}: clip must be a clip name or \"all\", got {clip!r}")
        _check_args(command, rig, args, where)
        clips = _clips_of(rig) if clip == "all" else [clip]
        if clip == "all" and spec.get("output") is not None:
            raise BatchError(f"{where}: output names one file; with clip = \"all\" leave it out (<rig>/<clip>.usdc)")
        for c in clips:
            stem = _stem(rig)
            if stem in clash and Path(rig).suffix:
                stem = f"{stem}_{Path(rig).suffix.lstrip('.').lower()}"
            rel, path = _output_of(spec.get("output"), rig, c, outdir, where, stem)
            if rel in seen:
                raise BatchError(f"{where}: output {rel!r} is also {seen[rel]}'s; give each job its own output")
            seen[rel] = where
            jobs.append(Job(rel, rig, command, c, frames, args, path))
    return jobs


def read_jobs(path: str | Path, outdir: str | Path) -> list[Job]:
    """The jobs of a JOBS file: a TOML file of ``[[job]]`` tables, each with ``rig`` (a rig
    file or TOML scene, relative to the JOBS file, or a shipped scene name), ``command``
    (``simulate``, default, ``skin`` or ``pop``), ``clip`` (a name or ``"all"``: one job per
    clip), ``frames`` (``"A:B"``), ``output`` (relative to OUTDIR; default
    ``<rig stem>/<clip>.usdc``) and ``args`` (the command's own options).

    Raises:
        BatchError: an unreadable file or a bad job, naming the file, the job and the key.
    """
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise BatchError(f"{p}: cannot read the jobs: {exc}") from None
    unknown = sorted(set(data) - {"job"})
    if unknown:
        raise BatchError(f"{p}: unknown key(s) {unknown}; a JOBS file holds [[job]] tables")
    tables = data.get("job")
    if not isinstance(tables, list) or not tables:
        raise BatchError(f"{p}: no jobs; a JOBS file holds [[job]] tables (rig, command, clip, frames, output, args)")
    specs = []
    for k, table in enumerate(tables, start=1):
        where = f"{p}: job {k}"
        if not isinstance(table, dict):
            raise BatchError(f"{where} must be a table")
        spec = dict(table)
        rig = spec.get("rig")
        if isinstance(rig, str) and (Path(rig).suffix or "/" in rig) and not Path(rig).is_absolute():
            spec["rig"] = str((p.parent / rig).resolve())
        elif isinstance(rig, str) and Path(rig).is_absolute():
            spec["rig"] = str(Path(rig).resolve())
        specs.append((spec, f"{where} ({table.get('rig', '?')})"))
    return _make_jobs(specs, Path(outdir).resolve())


def jobs_for_rigs(patterns: list[str], outdir: str | Path, *, command: str = "simulate", clips: str | None = None,
                  frames: str | None = None, args: list[str] | None = None) -> list[Job]:
    """One job per rig (file paths or glob patterns, or shipped scene names) and, with
    ``clips="all"``, per clip; outputs ``<rig stem>/<clip>.usdc``.

    Raises:
        BatchError: a pattern that matches nothing, or a bad option.
    """
    rigs: list[str] = []
    for pattern in patterns:
        matched = sorted(glob.glob(pattern)) if glob.has_magic(pattern) else [pattern]
        if not matched:
            raise BatchError(f"{pattern}: matches no file")
        rigs += [str(Path(m).resolve()) if Path(m).is_file() else m for m in matched]
    specs = [({"rig": r, "command": command, "clip": clips, "frames": frames, "args": list(args or [])}, r)
             for r in rigs]
    return _make_jobs([({k: v for k, v in s.items() if v is not None}, w) for s, w in specs], Path(outdir).resolve())


# ------------------------------------------------------------------------------ the runs
def _write_text(path: Path, text: str) -> None:
    """Write ``text`` atomically: to a temporary file beside ``path``, then renamed onto it."""
    staged = path.with_name(f".{path.name}.tmp")
    try:
        staged.write_text(text)
        os.replace(staged, path)
    finally:
        staged.unlink(missing_ok=True)


def _load_manifest(outdir: Path) -> dict:
    p = outdir / _MANIFEST
    if not p.is_file():
        return {}
    try:
        data = json.loads(p.read_text())
    except (OSError, json.JSONDecodeError):
        return {}  # unreadable: every job runs again
    return data.get("jobs", {}) if isinstance(data, dict) else {}


def _last_line(path: Path) -> str:
    try:
        lines = [ln.strip() for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return ""
    errors = [ln for ln in lines if ln.startswith("warpskin:") and "warning:" not in ln]
    return (errors or lines or [""])[-1]


def _log_name(job_id: str) -> str:
    return job_id.replace("/", "__")


def _fmt_seconds(s: float) -> str:
    return f"{s:.0f} s" if s < 120 else f"{s / 60:.1f} min"


def _device_of(job: Job) -> str:
    """The ``--device`` a job's args give (``cpu`` where they give none)."""
    args = job.args
    for k, a in enumerate(args):
        if a == "--device" and k + 1 < len(args):
            return args[k + 1]
        if a.startswith("--device="):
            return a.split("=", 1)[1]
    return "cpu"


class _Processes:
    """Jobs as processes of this machine, ``capacity`` at a time, their output in log files.
    A job on ``--device cuda`` (no index) gets a GPU of its own, ``CUDA_VISIBLE_DEVICES`` set
    to one of ``gpus`` free ones, and waits while none is free."""

    def __init__(self, capacity: int, env: dict | None, gpus: int = 0) -> None:
        self.capacity, self.env = capacity, env
        self.gpus = gpus
        self.free_gpus = list(range(gpus))
        self.running: dict[str, tuple] = {}
        self.gpu_of: dict[str, int] = {}

    def can_start(self, job: Job) -> bool:
        return _device_of(job) != "cuda" or bool(self.free_gpus) or not self.gpus

    def start(self, job: Job, out: Path, err: Path) -> dict:
        """Start ``job`` (its output to the files ``out`` and ``err``); returns what its
        manifest entry records of the run: its ``pid``, and its ``gpu`` where it has one."""
        env = self.env
        if _device_of(job) == "cuda" and self.free_gpus:
            gpu = self.free_gpus.pop(0)
            self.gpu_of[job.id] = gpu
            env = {**(os.environ if env is None else env), "CUDA_VISIBLE_DEVICES": str(gpu)}
        stdout, stderr = open(out, "w"), open(err, "w")
        proc = subprocess.Popen(job.argv(), stdout=stdout, stderr=stderr, env=env, start_new_session=True,
                                preexec_fn=_end_with_parent(os.getpid()))
        self.running[job.id] = (proc, stdout, stderr)
        return {"pid": proc.pid, **({"gpu": self.gpu_of[job.id]} if job.id in self.gpu_of else {})}

    def finished(self) -> list[tuple[str, int]]:
        """``[(job id, exit code)]`` of the jobs that ended since the last call."""
        time.sleep(0.05)
        out = []
        for jid in [j for j, (p, *_) in self.running.items() if p.poll() is not None]:
            proc, stdout, stderr = self.running.pop(jid)
            stdout.close()
            stderr.close()
            if jid in self.gpu_of:
                self.free_gpus.append(self.gpu_of.pop(jid))
            out.append((jid, proc.returncode))
        return out

    def close(self) -> None:
        pass

    def stop(self) -> None:
        for proc, *_ in self.running.values():  # an interrupted batch leaves no worker behind
            with contextlib.suppress(OSError):
                proc.terminate()
        for proc, stdout, stderr in self.running.values():
            with contextlib.suppress(subprocess.TimeoutExpired, OSError):
                proc.wait(timeout=10)
            stdout.close()
            stderr.close()


def _end_with_parent(parent: int):
    """A ``preexec_fn`` that makes a worker end with the batch that started it, however the batch
    ends (SIGKILL included): on Linux, the kernel sends the worker SIGTERM when its parent dies
    (``prctl(PR_SET_PDEATHSIG)``), which keeps its finished frames and exits 3 as a failed run
    does; a parent already gone when it is set is caught by the parent id check. Elsewhere
    ``None`` (a batch stopped by a signal it can catch still stops its workers,
    :meth:`_Processes.stop`). Workers run in a session (process group) of their own, so a
    terminal's Ctrl-C reaches the batch, which ends them, rather than each of them."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        import ctypes

        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None

    def end_with_parent() -> None:
        prctl(1, int(signal.SIGTERM), 0, 0, 0)  # PR_SET_PDEATHSIG = 1
        if os.getppid() != parent:  # the batch died before the line above
            os.kill(os.getpid(), signal.SIGTERM)

    return end_with_parent


def _cuda_device_count() -> int:
    import warp as wp

    try:
        return int(wp.get_cuda_device_count())
    except Exception:  # no driver: no GPU
        return 0


def _ray_job(argv: list[str]) -> tuple[int, str, str]:
    """A job on a Ray worker: its command line run by that worker's Python (a process of its
    own, as locally), returning ``(exit code, stdout, stderr)``."""
    proc = subprocess.run([sys.executable, *argv[1:]], capture_output=True, text=True)
    return proc.returncode, proc.stdout, proc.stderr


class _RayTasks:
    """Jobs as Ray tasks (``num_gpus=1`` each for a CUDA job), as many at a time as the cluster
    schedules; their output comes back with the result and goes to the log files here. The
    bakes are written where the job's output path points on the worker: give a path every
    node sees (a shared filesystem) on a cluster of several machines."""

    def __init__(self, address: str, retries: int) -> None:
        try:
            import ray
        except ImportError:
            raise BatchError("--ray needs Ray: pip install 'warpskin[farm]'") from None
        self.ray = ray
        self.owned = not ray.is_initialized()  # shut down at the end what this batch started
        if self.owned:
            kw = {"include_dashboard": False, "log_to_driver": False, "logging_level": "ERROR"}
            if address == "auto":
                try:
                    ray.init(address="auto", **kw)  # the cluster `ray start` made
                except ConnectionError:
                    ray.init(**kw)  # else a local one
            else:
                try:
                    ray.init(address=address, **kw)
                except ConnectionError as exc:
                    raise BatchError(f"--ray {address}: no Ray cluster there ({exc})") from None
        self.remote = ray.remote(_ray_job)
        self.retries = retries
        self.capacity = 1 << 30  # Ray schedules by the cluster's resources
        self.running: dict = {}  # object ref -> (job id, out, err)

    def can_start(self, job: Job) -> bool:
        return True

    def start(self, job: Job, out: Path, err: Path) -> dict:
        gpu = _device_of(job).startswith("cuda")
        ref = self.remote.options(num_cpus=1, num_gpus=1 if gpu else 0, max_retries=self.retries,
                                  retry_exceptions=False).remote(job.argv())
        self.running[ref] = (job.id, out, err)
        return {}

    def finished(self) -> list[tuple[str, int]]:
        if not self.running:
            return []
        done, _ = self.ray.wait(list(self.running), num_returns=1, timeout=0.5)
        out = []
        for ref in done:
            jid, stdout, stderr = self.running.pop(ref)
            try:
                rc, text_out, text_err = self.ray.get(ref)
            except self.ray.exceptions.RayError as exc:  # the worker died past its retries
                rc, text_out, text_err = -signal.SIGKILL, "", f"warpskin: error: the Ray worker died: {exc}"
            stdout.write_text(text_out)
            stderr.write_text(text_err)
            out.append((jid, rc))
        return out

    def stop(self) -> None:
        for ref in self.running:
            with contextlib.suppress(Exception):
                self.ray.cancel(ref, force=True)

    def close(self) -> None:
        if self.owned:
            self.ray.shutdown()


def run_batch(jobs: list[Job], outdir: str | Path, *, workers: int | None = None, retries: int = 1,
              progress: bool = True, env: dict | None = None, ray: str | None = None,
              gpus: int | None = None) -> BatchResult:
    """Run ``jobs``: on this machine, ``workers`` processes at a time (default: one per core),
    each job in its own process; or, with ``ray``, as tasks of a Ray cluster.

    Args:
        jobs: The jobs (:func:`read_jobs`, :func:`jobs_for_rigs`).
        outdir: Where the bakes, ``manifest.json``, ``index.md`` and ``logs/`` go.
        workers: Jobs at a time on this machine, >= 1 (default: one per core, or one per GPU
            when every job runs on ``--device cuda``; not with ``ray``: the cluster's
            resources decide).
        retries: Runs again a job whose process died of a signal (killed, out of memory), at
            most this many times (with ``ray`` also a task whose worker died, by Ray).
        progress: One status line on stderr (done / running / failed, eta).
        env: The jobs' environment on this machine (default this process's).
        ray: A Ray cluster's address, or ``"auto"`` (the cluster ``ray start`` made, else a
            local one); needs the ``farm`` extra.
        gpus: CUDA devices of this machine for the jobs on ``--device cuda`` (each gets one of
            its own, ``CUDA_VISIBLE_DEVICES``); default: Warp's count, where a job asks.

    Returns:
        A :class:`BatchResult`; the manifest is written after every job.

    Raises:
        BatchError: bad ``workers`` or ``retries``, or no Ray.
    """
    from . import __version__

    cuda = any(_device_of(j) == "cuda" for j in jobs)
    if gpus is None:
        gpus = _cuda_device_count() if cuda and not ray else 0
    if workers is None:  # one per core; one per GPU for a batch of CUDA jobs
        workers = gpus if cuda and gpus and all(_device_of(j).startswith("cuda") for j in jobs) else (os.cpu_count() or 1)
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise BatchError(f"--workers must be a whole number >= 1, got {workers!r}")
    if isinstance(retries, bool) or not isinstance(retries, int) or retries < 0:
        raise BatchError(f"--retries must be a whole number >= 0, got {retries!r}")
    runner = _RayTasks(ray, retries) if ray else _Processes(workers, env, gpus)
    out = Path(outdir)
    logs = out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    old = _load_manifest(out)
    entries: dict[str, dict] = {}
    result = BatchResult(entries=entries)
    t0 = time.perf_counter()
    queue: list[Job] = []
    by_id = {job.id: job for job in jobs}
    for job in jobs:
        key = job.key(__version__)
        prev = old.get(job.id)
        if prev and prev.get("key") == key and prev.get("status") == "ok" and job.output.is_file():
            entries[job.id] = prev
            result.skipped.append(job.id)
            continue
        entries[job.id] = {"key": key, "rig": job.rig, "command": job.command, "clip": job.clip,
                           "frames": job.frames, "args": job.args, "output": job.id, "status": "queued",
                           "attempts": 0, "warpskin": __version__}
        queue.append(job)

    def save() -> None:
        _write_text(out / _MANIFEST, json.dumps({"warpskin": __version__, "jobs": entries}, indent=1))

    save()
    started: dict[str, float] = {}
    durations: list[float] = []
    tty = progress and sys.stderr.isatty()
    slots = workers if not ray else None

    def status() -> None:
        if not progress:
            return
        done = len(result.ran) - len(result.failed)
        left = len(queue) + len(started)
        eta = (sum(durations) / len(durations)) * math.ceil(left / (slots or max(len(started), 1))) \
            if durations and left else 0.0
        line = (f"batch: {done} done, {len(started)} running, {len(result.failed)} failed, {left} left"
                + (f", eta {_fmt_seconds(eta)}" if eta else "") + f" ({len(result.skipped)} up to date)")
        print(("\r" + line.ljust(78)) if tty else line, end="" if tty else "\n", file=sys.stderr, flush=True)

    try:
        while queue or started:
            while queue and len(started) < runner.capacity:
                job = next((j for j in queue if runner.can_start(j)), None)
                if job is None:
                    break  # every queued job waits for a GPU
                queue.remove(job)
                e = entries[job.id]
                e["attempts"] += 1
                job.output.parent.mkdir(parents=True, exist_ok=True)
                e.update(runner.start(job, logs / f"{_log_name(job.id)}.out", logs / f"{_log_name(job.id)}.err"),
                         status="running")
                started[job.id] = time.perf_counter()
                save()
                status()
            for jid, rc in runner.finished():
                job, e = by_id[jid], entries[jid]
                e.pop("pid", None)
                e["exit_code"] = rc
                e["seconds"] = round(time.perf_counter() - started.pop(jid), 3)
                died = rc < 0 or rc in _RETRYABLE_EXITS
                if died and e["attempts"] <= retries:
                    e["status"] = "retrying"
                    e["message"] = f"its process died ({_signal_name(rc)}); run again"
                    queue.append(job)
                    save()
                    status()
                    continue
                if jid not in result.ran:
                    result.ran.append(jid)
                if rc == 0 and job.output.is_file():
                    durations.append(e["seconds"])
                    e.update(status="ok", message="")
                    e["summary"] = _summary(logs / f"{_log_name(jid)}.out")
                else:
                    e["status"] = "failed"
                    e["message"] = (f"its process died ({_signal_name(rc)})" if died else
                                    _last_line(logs / f"{_log_name(jid)}.err") or f"exit {rc}, no output")
                    result.failed.append(jid)
                save()
                status()
    except BaseException:
        runner.stop()
        for jid in started:
            entries[jid].update(status="interrupted")
            entries[jid].pop("pid", None)
        save()
        raise
    finally:
        runner.close()
    if tty:
        print(file=sys.stderr)
    result.seconds = time.perf_counter() - t0
    _write_index(out, jobs, entries, result)
    return result


def _signal_name(rc: int) -> str:
    n = -rc if rc < 0 else rc - 128
    try:
        return signal.Signals(n).name
    except ValueError:
        return f"exit {rc}"


def _summary(path: Path) -> dict:
    """The few figures of a job's JSON summary the index shows."""
    try:
        s = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return {}
    keep = ("frames", "device", "vertices", "particles", "max_volume_deviation", "max_volume_deviation_lbs",
            "mean_step_ms", "groups")
    return {k: s[k] for k in keep if k in s}


def _figures(summary: dict) -> str:
    """A job's summary in a few words: device, frames, cost, volume beside LBS."""
    parts = []
    if "device" in summary:
        parts.append(str(summary["device"]))
    if "frames" in summary:
        parts.append(f"{summary['frames']} frames")
    if "mean_step_ms" in summary:
        parts.append(f"{summary['mean_step_ms']:.1f} ms/step")
    if "max_volume_deviation" in summary:
        lbs = summary.get("max_volume_deviation_lbs")
        parts.append(f"volume {100 * summary['max_volume_deviation']:.2f} %"
                     + (f" (LBS {100 * lbs:.2f} %)" if lbs is not None else ""))
    if summary.get("groups"):
        parts.append(f"groups {', '.join(map(str, summary['groups']))}")
    return ", ".join(parts)


def _report_of(job: Job) -> str | None:
    """The report folder a job's args ask for (``--report DIR``), if any."""
    for k, a in enumerate(job.args):
        if a == "--report" and k + 1 < len(job.args):
            return job.args[k + 1]
    return None


def _thumbnail(out: Path, job: Job) -> str:
    """The index's picture of a finished job (``thumbs/<job>.png``, drawn by
    :func:`~warpskin.thumbnail.write_thumbnail` unless newer than the bake), as Markdown;
    empty where it cannot be drawn (no matplotlib, no mesh)."""
    target = out / "thumbs" / f"{_log_name(job.id)}.png"
    try:
        if not target.is_file() or target.stat().st_mtime < job.output.stat().st_mtime:
            write_thumbnail(job.output, target)
    except (ImportError, ValueError, OSError):
        return ""
    return f"![{job.id}]({target.relative_to(out).as_posix()})"


def _write_index(out: Path, jobs: list[Job], entries: dict, result: BatchResult) -> None:
    """``index.md``: every job's status, time, figures (device, frames, cost, volume beside
    LBS), a picture of its bake at its middle frame beside LBS (:func:`_thumbnail`), its bake
    and report, or its message; written atomically."""
    rows = ["| job | command | status | time | figures | output or message | picture |",
            "|---|---|---|---|---|---|---|"]
    for job in jobs:
        e = entries[job.id]
        picture = ""
        if e.get("status") == "ok":
            picture = _thumbnail(out, job)
            what = f"[{job.id}]({job.id})"
            report = _report_of(job)
            if report:
                what += f", [report]({Path(report).resolve().as_uri()})"
        else:
            what = f"exit {e.get('exit_code')}: " + str(e.get("message", "")).replace("|", "/")
        seconds = e.get("seconds")
        rows.append(f"| {job.id} | {job.command} | {e.get('status')} | "
                    f"{'' if seconds is None else f'{seconds:.1f} s'} | {_figures(e.get('summary', {}))} | {what} | "
                    f"{picture} |")
    head = (f"# warpskin batch\n\n{len(jobs)} jobs: {len(jobs) - len(result.failed)} succeeded "
            f"({len(result.skipped)} up to date), {len(result.failed)} failed; {result.seconds:.1f} s.\n\n")
    _write_text(out / "index.md", head + "\n".join(rows) + "\n")


# ------------------------------------------------------------------------------ the command
@dataclass
class BatchOptions:
    """``warpskin batch`` (declared settings, :mod:`warpskin.settings`)."""

    jobs: list = setting([], "strings", "a JOBS file (TOML, [[job]] tables), or rig files / glob patterns / shipped "
                         "scenes", cli="jobs", metavar="JOBS")
    output: str = setting("", "string", "where the bakes, manifest.json and index.md go", cli=("-o", "--output"),
                          metavar="OUTDIR")
    workers: int | None = setting(None, "integer", "jobs at a time on this machine (default: one per core)", low=1,
                                  optional=True, cli="--workers")
    ray: str | None = setting(None, "string", "run each job as a task of the Ray cluster at ADDRESS, or 'auto' (the "
                              "cluster `ray start` made, else a local one); pip install 'warpskin[farm]'",
                              optional=True, cli="--ray", metavar="ADDRESS")
    retries: int = setting(1, "integer", "runs again a job whose process died, this many times (default 1)", low=0,
                           cli="--retries")
    command: str = setting("simulate", "string", "with rig files: what each job runs", choices=COMMANDS,
                           cli="--command")
    clips: str | None = setting(None, "string", "with rig files: a clip, or all of them (one job each)",
                                optional=True, cli="--clips", metavar="NAME|all")
    frames: str | None = setting(None, "string", "with rig files: the frames of every job", optional=True,
                                 cli="--frames", metavar="A:B")
    args: str = setting("", "string", "with rig files: the command's own options, as --args='--bpm 120 --lbs'",
                        cli="--args", metavar="'OPTIONS'")
    quiet: bool = setting(False, "bool", "no progress line", cli="--quiet")
    json: bool = setting(False, "bool", "print the manifest's entries as JSON", cli="--json")


def add_parser(sub) -> None:
    """Add ``warpskin batch`` to the command parser ``sub`` (options from :class:`BatchOptions`)."""
    s = sub.add_parser("batch", help="bake many rigs x clips, each job in its own process; resumable (JSON manifest)")
    add_option(s, BatchOptions, "jobs", nargs="+")
    add_option(s, BatchOptions, "output", required=True)
    for name in ("workers", "ray", "retries", "command", "clips", "frames", "args", "quiet", "json"):
        add_option(s, BatchOptions, name)


def cmd_batch(args: argparse.Namespace) -> int:
    first = Path(args.jobs[0])
    is_jobs_file = len(args.jobs) == 1 and first.suffix.lower() == ".toml" and first.is_file() and _has_jobs(first)
    if is_jobs_file:
        jobs = read_jobs(first, args.output)
    else:
        jobs = jobs_for_rigs(args.jobs, args.output, command=args.command, clips=args.clips, frames=args.frames,
                             args=shlex.split(args.args))
    if args.ray and args.workers is not None:
        raise BatchError("--workers is for this machine; with --ray the cluster's resources decide")
    result = run_batch(jobs, args.output, workers=args.workers, retries=args.retries, progress=not args.quiet,
                       ray=args.ray)
    if args.json:
        print(json.dumps(result.entries, indent=1))
    else:
        width = max(len(j.id) for j in jobs)
        for job in jobs:
            e = result.entries[job.id]
            state = "up to date" if job.id in result.skipped else e["status"]
            note = "" if e["status"] == "ok" else f"  exit {e.get('exit_code')}: {e.get('message', '')}"
            seconds = e.get("seconds")
            print(f"{job.id:{width}s}  {state:10s} {'' if seconds is None else f'{seconds:7.1f} s'}{note}")
        print(f"{len(jobs)} jobs in {result.seconds:.1f} s: {len(result.ran) - len(result.failed)} ran, "
              f"{len(result.skipped)} up to date, {len(result.failed)} failed; {Path(args.output) / 'index.md'}")
    return result.exit_code


def _has_jobs(path: Path) -> bool:
    try:
        return "job" in tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return True  # read_jobs names the problem
