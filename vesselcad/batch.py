"""Batch conversion: many two-run cases, in parallel, resumable, one failure never stops the rest.

A batch input is either a folder of case folders (each holding the two runs of
one case) or a CSV manifest. Every case is reconstructed by
:func:`vesselcad.reconstruct` in a worker process of its own and written to
``OUT/<case>/`` exactly as ``vesselcad reconstruct`` writes it, plus a
``case.json`` record (status, message, numbers, input fingerprint). A case
whose record says it finished on the same inputs and options is skipped when
the batch is run again (``force`` re-runs it); cases that failed are retried.
``OUT/summary.csv`` and ``OUT/summary.json`` list every case and are rewritten
after each one finishes, so an interrupted batch still leaves a summary.

Parallelism is a local process pool, or an existing Dask distributed cluster
(``scheduler``: its address or a ``distributed.Client``) for archives larger
than one machine; there the workers must see the input and output paths
(shared file system).
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import os
import re
import time
import traceback
from collections.abc import Callable, Iterable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path
from typing import Any

from .errors import ArgumentError, InputFileError, VesselcadError
from .io import atomic_write_text

__all__ = ["BatchCase", "BatchResult", "find_cases", "run_batch", "SUMMARY_COLUMNS"]

#: Statuses a case can end with: ``ok`` a tree was written; ``no_tree`` the runs were
#: read but gave no tree (the message names the stage); ``error`` bad input or a crash;
#: ``skipped`` finished in an earlier run on the same inputs (its record is kept).
STATUSES = ("ok", "no_tree", "error", "skipped")

#: Columns of ``summary.csv``.
SUMMARY_COLUMNS = (
    "case", "status", "message", "seconds", "frame_a", "frame_b", "phase_error_mm", "branches_ok",
    "branches_total", "reprojection_mean_px", "reprojection_mean_mm", "solid_valid", "solid_watertight",
    "solid_tree_share", "refined", "warnings", "out", "run_a", "run_b",
)

_MANIFEST_ID = ("case", "id", "case_id")
# reconstruct()'s defaults, so that the API and the CLI fingerprint the same options alike
_DEFAULTS = {"method": "nurbs", "model": None, "objects": "auto", "refine": True, "solid": True,
             "tta": "chosen", "frame_search": "all", "off_surface_sigmas": 4.0, "max_side": 512}
_RECORD = "case.json"
_SAFE_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


@dataclass(frozen=True)
class BatchCase:
    """One case of a batch: two runs and optional per-run geometry overrides.

    Attributes
    ----------
    id : str
        Case name; also the name of its output folder.
    run_a, run_b : pathlib.Path
        The two runs (XA DICOM files or frame folders).
    geometry_a, geometry_b : dict, path or None
        ``CArmView`` entries or a view.json path overriding each file's geometry.
    frames : (int, int) or None
        Frame pair to use instead of motion phase matching.
    problem : str or None
        Why the case cannot be run as found (e.g. three DICOM files in its
        folder); such a case ends with status ``error`` and this message.
    """

    id: str
    run_a: Path | None
    run_b: Path | None
    geometry_a: Any = None
    geometry_b: Any = None
    frames: tuple[int, int] | None = None
    problem: str | None = None


@dataclass
class BatchResult:
    """What a batch did: one record per case (the rows of ``summary.json``).

    Attributes
    ----------
    cases : list of dict
        Per case: ``case``, ``status`` (one of ``ok``, ``no_tree``, ``error``,
        ``skipped``), ``message``, ``seconds``, numbers of the reconstruction
        and, for errors, ``error_type`` and ``traceback``.
    out : pathlib.Path
        The output folder.
    seconds : float
        Wall time of the whole batch.
    """

    cases: list[dict[str, Any]]
    out: Path
    seconds: float = 0.0
    counts: dict[str, int] = field(default_factory=dict)

    @property
    def failed(self) -> list[dict[str, Any]]:
        """Records of the cases that gave no tree (status ``no_tree`` or ``error``)."""
        return [c for c in self.cases if c["status"] in ("no_tree", "error")]

    @property
    def ok(self) -> bool:
        """True when no case failed."""
        return not self.failed

    def __repr__(self) -> str:
        counts = ", ".join(f"{k} {v}" for k, v in self.counts.items() if v)
        return f"<BatchResult {len(self.cases)} cases ({counts}) in {self.seconds:.1f} s, {self.out}>"


# ----------------------------------------------------------------------------- finding cases


def find_cases(source: str | os.PathLike) -> list[BatchCase]:
    """The cases of a batch input.

    Parameters
    ----------
    source : path
        A folder of case folders, or a CSV manifest.

        *Case folders*: every sub-folder of ``source`` (in name order) is one
        case named after it. Its runs are its two DICOM files (``*.dcm``, or
        any file with the DICOM preamble) in name order, or its two frame
        folders (sub-folders holding a ``view.json``). Optional
        ``geometry.json`` (both runs), ``geometry_a.json`` and
        ``geometry_b.json`` beside them override the files' geometry.

        *Manifest*: a CSV file with a header row and the columns ``case``
        (or ``id``), ``run_a``, ``run_b``, and optionally ``geometry``,
        ``geometry_a``, ``geometry_b`` (a view.json path or an inline JSON
        object) and ``frame_a``, ``frame_b``. Relative paths are relative to
        the manifest's folder.

    Returns
    -------
    list of BatchCase
        A case that cannot be run as found (wrong number of runs) is still
        returned, with ``problem`` set, so that the batch reports it.

    Raises
    ------
    InputFileError
        ``source`` does not exist, or a folder holds no case folders.
    ArgumentError
        A manifest lacks a required column, repeats a case name, or has a
        case name that cannot be a folder name.
    """
    src = Path(source)
    if not src.exists():
        raise InputFileError(f"{src}: no such batch input (expected a folder of case folders or a CSV "
                             "manifest)")
    cases = _from_manifest(src) if src.is_file() else _from_folder(src)
    seen: set[str] = set()
    for c in cases:
        if c.id in seen:
            raise ArgumentError(f"{src}: case {c.id!r} appears twice")
        seen.add(c.id)
    return cases


def _is_dicom(p: Path) -> bool:
    if p.suffix.lower() in (".dcm", ".dicom"):
        return True
    if p.suffix:  # a named non-DICOM file (.json, .png, .txt ...)
        return False
    try:
        with p.open("rb") as fh:
            head = fh.read(132)
    except OSError:
        return False
    return len(head) == 132 and head[128:] == b"DICM"


def _from_folder(src: Path) -> list[BatchCase]:
    folders = sorted((d for d in src.iterdir() if d.is_dir() and not d.name.startswith(".")),
                     key=lambda d: d.name)
    if not folders:
        raise InputFileError(f"{src}: no case folders in it (expected one sub-folder per case holding "
                             "its two runs, or give a CSV manifest)")
    cases = []
    for d in folders:
        runs = sorted(p for p in d.iterdir() if p.is_file() and not p.name.startswith(".") and _is_dicom(p))
        if not runs:
            runs = sorted(p for p in d.iterdir() if p.is_dir() and (p / "view.json").is_file())
        geo = {k: d / f"{k}.json" for k in ("geometry", "geometry_a", "geometry_b")}
        ga = geo["geometry_a"] if geo["geometry_a"].is_file() else None
        gb = geo["geometry_b"] if geo["geometry_b"].is_file() else None
        if geo["geometry"].is_file():
            ga, gb = ga or geo["geometry"], gb or geo["geometry"]
        problem = None
        if len(runs) != 2:
            found = ", ".join(p.name for p in runs) or "none"
            problem = (f"{d}: expected exactly two runs (DICOM files or frame folders with view.json), found "
                       f"{len(runs)} ({found}); list the pair in a CSV manifest instead")
            runs = [None, None]
        cases.append(BatchCase(_case_id(d.name, src), runs[0], runs[1], ga, gb, None, problem))
    return cases


def _case_id(name: str, src: Path) -> str:
    name = name.strip()
    if not _SAFE_ID.match(name):
        raise ArgumentError(f"{src}: case name {name!r} cannot be used as a folder name (letters, digits, "
                            "'.', '_' and '-', not starting with '.')")
    return name


def _from_manifest(src: Path) -> list[BatchCase]:
    try:
        text = src.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(f"{src}: cannot read the manifest ({exc})") from None
    reader = csv.DictReader(io.StringIO(text))
    cols = [c.strip().lower() for c in (reader.fieldnames or [])]
    reader.fieldnames = cols
    id_col = next((c for c in _MANIFEST_ID if c in cols), None)
    missing = [c for c, ok in (("case", id_col), ("run_a", "run_a" in cols), ("run_b", "run_b" in cols))
               if not ok]
    if missing:
        raise ArgumentError(f"{src}: manifest lacks the column(s) {', '.join(missing)} (header: "
                            f"{', '.join(cols) or 'none'}); expected case,run_a,run_b[,geometry_a,"
                            "geometry_b,frame_a,frame_b]")
    cases = []
    base = src.parent
    for line, row in enumerate(reader, start=2):
        row = {k: (v or "").strip() for k, v in row.items() if k}
        if not any(row.values()):
            continue
        cid = _case_id(row[id_col], src) if row[id_col] else f"case{line - 1:04d}"
        where = f"{src}, line {line} (case {cid})"
        runs = [base / row[k] if row[k] else None for k in ("run_a", "run_b")]
        geo = {k: _manifest_geometry(row.get(k, ""), base, where, k) for k in
               ("geometry", "geometry_a", "geometry_b")}
        frames = None
        problem = None
        if None in runs:
            problem = f"{where}: run_a and run_b are both needed"
        fa, fb = row.get("frame_a", ""), row.get("frame_b", "")
        if fa or fb:
            try:
                frames = (int(fa), int(fb))
            except ValueError:
                problem = f"{where}: frame_a/frame_b must be two integers, got {fa!r}, {fb!r}"
        cases.append(BatchCase(cid, runs[0], runs[1], geo["geometry_a"] or geo["geometry"],
                               geo["geometry_b"] or geo["geometry"], frames, problem))
    if not cases:
        raise InputFileError(f"{src}: the manifest lists no cases")
    return cases


def _manifest_geometry(value: str, base: Path, where: str, column: str) -> Any:
    if not value:
        return None
    if value.startswith("{"):
        try:
            return json.loads(value)
        except json.JSONDecodeError as exc:
            raise ArgumentError(f"{where}: column {column} is not valid JSON ({exc})") from None
    return base / value


# ----------------------------------------------------------------------------- one case


def _fingerprint(case: BatchCase, options: dict[str, Any]) -> str:
    """Hash of the inputs (paths, sizes, modification times) and options, for resuming."""
    h = hashlib.sha256()
    for p in (case.run_a, case.run_b, case.geometry_a, case.geometry_b):
        if isinstance(p, Path):
            files = sorted(p.rglob("*")) if p.is_dir() else [p]
            for f in files:
                try:
                    st = f.stat()
                    h.update(f"{f.resolve()}|{st.st_size}|{st.st_mtime_ns}\n".encode())
                except OSError:
                    h.update(f"{f}|missing\n".encode())
        else:
            h.update(json.dumps(p, sort_keys=True, default=str).encode())
    # an option at a default it had before it existed is left out, so older finished cases still match
    opts = {k: v for k, v in options.items()
            if not (k == "frame_search" and v == "all") and not (k == "off_surface_sigmas" and v == 4.0)
            and not (k == "max_side" and v == 512)}
    h.update(json.dumps({"frames": case.frames, **opts}, sort_keys=True, default=str).encode())
    return h.hexdigest()[:16]


_SEGMENTERS: dict[tuple[str, int], Any] = {}


def _segmenter(model: str | None, threads: int):
    """One loaded model per worker process (loading it costs more than a small case)."""
    from .segment import Segmenter

    key = (str(model), threads)
    if key not in _SEGMENTERS:
        _SEGMENTERS[key] = Segmenter(model, threads=threads)
    return _SEGMENTERS[key]


def process_case(case: BatchCase, out: str | os.PathLike, options: dict[str, Any]) -> dict[str, Any]:
    """Reconstruct one case into ``out/<case.id>/`` and return its summary record.

    Never raises for a problem of the case itself: a bad file, a stage that
    gives no tree or an unexpected exception end as the record's ``status``
    and ``message`` (with the traceback for unexpected ones). The record is
    also written to ``out/<case.id>/case.json``.
    """
    from .pipeline import ReconstructionError, reconstruct

    opts = dict(options)
    html = opts.pop("html", True)
    threads = int(opts.pop("threads", 1))
    fingerprint = opts.pop("fingerprint", "")
    case_out = Path(out) / case.id
    rec_out: dict[str, Any] = {"case": case.id, "run_a": str(case.run_a or ""),
                               "run_b": str(case.run_b or ""), "out": str(case_out),
                               "fingerprint": fingerprint}
    t0 = time.perf_counter()
    try:
        if case.problem:
            raise InputFileError(case.problem)
        opts["model"] = _segmenter(opts.get("model"), threads)
        rec = reconstruct(case.run_a, case.run_b, geometry_a=case.geometry_a, geometry_b=case.geometry_b,
                          frames=case.frames, progress=False, **opts)
        rec.write(case_out, html=html)
        rep = json.loads((case_out / "report.json").read_text())  # written just now; no second check
        e = rec.errors
        solid = rep.get("solid") or {}
        n_rejected = len(rec.branches) - len(rec.ok_branches)
        rec_out.update(
            status="ok" if rec.tree is not None else "no_tree",
            message=(f"{len(rec.ok_branches)} branches" + (f", {n_rejected} rejected" if n_rejected else "")
                     if rec.tree is not None else "no branch reconstructed"),
            frame_a=rep["frame_a"], frame_b=rep["frame_b"], phase_error_mm=rep["phase_error_mm"],
            branches_ok=len(rec.ok_branches), branches_total=len(rec.branches),
            reprojection_mean_px=round(e["mean_px"], 4) if e else None,
            reprojection_mean_mm=round(e["mean_mm"], 4) if e else None,
            solid_valid=solid.get("valid"), solid_watertight=solid.get("watertight"),
            solid_tree_share=solid.get("tree_share"),
            refined=rep["view_b"]["refined"], warnings=len(rec.warnings),
            timings_s={k: round(v, 3) for k, v in rec.timings.items()},
        )
    except ReconstructionError as exc:
        rec_out.update(status="no_tree", message=str(exc), error_type=type(exc).__name__)
    except VesselcadError as exc:
        rec_out.update(status="error", message=str(exc), error_type=type(exc).__name__)
    except Exception as exc:  # one bad case never loses the rest: record it, go on
        rec_out.update(status="error", message=f"{type(exc).__name__}: {exc}", error_type=type(exc).__name__,
                       traceback=traceback.format_exc())
    rec_out["seconds"] = round(time.perf_counter() - t0, 3)
    try:
        atomic_write_text(case_out / _RECORD, json.dumps(rec_out, indent=2) + "\n")
    except OSError as exc:
        rec_out.update(status="error", message=f"{case_out / _RECORD}: cannot write ({exc})")
    return rec_out


def _previous(case: BatchCase, out: Path, fingerprint: str) -> dict[str, Any] | None:
    p = out / case.id / _RECORD
    try:
        old = json.loads(p.read_text())
    except (OSError, ValueError):
        return None
    if old.get("status") in ("ok", "no_tree") and old.get("fingerprint") == fingerprint:
        return old
    return None


# ----------------------------------------------------------------------------- running many


def _init_worker(threads: int) -> None:
    # Keep every numeric library of a worker to its share of the cores.
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(threads)


def _crashed(case: BatchCase, fingerprint: str, out: Path, why: str) -> dict[str, Any]:
    return {"case": case.id, "status": "error", "message": why, "error_type": "WorkerCrash",
            "run_a": str(case.run_a or ""), "run_b": str(case.run_b or ""), "out": str(out / case.id),
            "fingerprint": fingerprint, "seconds": None}


def _run_pool(todo: list[tuple[BatchCase, dict]], out: Path, jobs: int, threads: int,
              done: Callable[[dict[str, Any]], None],
              fn: Callable[..., dict[str, Any]] = process_case) -> None:
    """Local process pool. A worker that dies (a crash in native code) breaks the pool:
    the cases it left unfinished are then re-run one per fresh process, so only the case
    that crashes again is lost."""
    ctx = get_context("spawn")  # no fork after OCCT/onnxruntime threads exist
    pending = list(todo)
    isolate = False
    while pending:
        width = 1 if isolate else min(jobs, len(pending))
        batch = pending[:1] if isolate else pending
        unfinished: list[tuple[BatchCase, dict]] = []
        with ProcessPoolExecutor(width, mp_context=ctx, initializer=_init_worker, initargs=(threads,)) as ex:
            futs: dict[Future, tuple[BatchCase, dict]] = {
                ex.submit(fn, c, str(out), o): (c, o) for c, o in batch}
            live = set(futs)
            while live:
                finished, live = wait(live, return_when=FIRST_COMPLETED)
                for f in finished:
                    try:
                        done(f.result())
                    except BrokenProcessPool:
                        unfinished.append(futs[f])
        pending = pending[len(batch):]
        if isolate:
            for c, o in unfinished:
                done(_crashed(c, o["fingerprint"], out, "the worker process died while reconstructing this "
                              "case (a crash in native code); the other cases are unaffected"))
        else:
            pending = unfinished
            isolate = bool(unfinished)


def _run_dask(todo: list[tuple[BatchCase, dict]], out: Path, scheduler: Any,
              done: Callable[[dict[str, Any]], None]) -> None:
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise ArgumentError("scheduler: needs the Dask distributed package "
                            "(pip install 'vesselcad[dask]')") from None
    client = scheduler if isinstance(scheduler, Client) else None
    if client is None:
        try:
            client = Client(str(scheduler), timeout="20s")
        except OSError as exc:
            raise ArgumentError(f"scheduler: cannot reach the Dask scheduler at {scheduler!r} "
                                f"({exc})") from None
    try:
        futs = {}
        for c, o in todo:
            f = client.submit(process_case, c, str(out), o, pure=False,
                              key=f"vesselcad-{c.id}-{o['fingerprint']}")
            futs[f] = (c, o)
        for f in as_completed(list(futs)):
            c, o = futs[f]
            try:
                done(f.result())
            except Exception as exc:  # a worker lost by the cluster (KilledWorker) and the like
                done(_crashed(c, o["fingerprint"], out, f"the Dask worker failed on this case: "
                              f"{type(exc).__name__}: {exc}"))
    finally:
        if client is not scheduler:
            client.close()


def _write_summary(out: Path, records: list[dict[str, Any]], extra: dict[str, Any]) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=SUMMARY_COLUMNS, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in records:
        w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in SUMMARY_COLUMNS})
    atomic_write_text(out / "summary.csv", buf.getvalue())
    atomic_write_text(out / "summary.json", json.dumps({**extra, "cases": records}, indent=2) + "\n")


def run_batch(
    source: str | os.PathLike | Iterable[BatchCase],
    out: str | os.PathLike,
    *,
    jobs: int = 1,
    force: bool = False,
    scheduler: Any = None,
    html: bool = True,
    progress: bool = False,
    **options: Any,
) -> BatchResult:
    """Reconstruct many cases, in parallel, resumably.

    Parameters
    ----------
    source : path or iterable of BatchCase
        A folder of case folders or a CSV manifest (see :func:`find_cases`),
        or the cases themselves.
    out : path
        Output folder; each case goes to ``out/<case>/``; ``summary.csv`` and
        ``summary.json`` list all cases.
    jobs : int
        Worker processes on this machine (each gets ``cores // jobs`` threads).
    force : bool
        Re-run cases that finished before on the same inputs.
    scheduler : str or distributed.Client, optional
        Run on this Dask distributed cluster instead of a local pool (its
        workers must see ``source`` and ``out`` at the same paths).
    html : bool
        Write report.html per case.
    progress : bool
        A progress bar over cases.
    **options
        Passed to :func:`vesselcad.reconstruct` (``method``, ``model``,
        ``objects``, ``refine``, ``solid``, ``tta``).

    Returns
    -------
    BatchResult

    Raises
    ------
    ArgumentError, InputFileError
        Bad arguments or a batch input that lists no case (problems of single
        cases never raise; they are in the result and the summary).
    """
    t0 = time.perf_counter()
    try:
        jobs = int(jobs)
    except (TypeError, ValueError):
        raise ArgumentError(f"jobs: expected a positive integer, got {jobs!r}") from None
    if jobs < 1:
        raise ArgumentError(f"jobs: expected a positive integer, got {jobs}")
    bad = set(options) - set(_DEFAULTS)
    if bad:
        raise ArgumentError(f"unknown reconstruct option(s) for a batch: {', '.join(sorted(bad))}")
    options = {**_DEFAULTS, **options}
    from .segment import BUNDLED_MODELS

    if options.get("model") is not None and options["model"] not in BUNDLED_MODELS:
        model = Path(options["model"])
        if not model.is_file():
            raise InputFileError(f"{model}: no such segmentation model")
        options["model"] = str(model.resolve())
    cases = find_cases(source) if isinstance(source, (str, os.PathLike)) else list(source)
    if not cases:
        raise ArgumentError("source: no cases")
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputFileError(f"{out}: cannot create the output folder ({exc})") from None
    threads = max(1, (os.cpu_count() or 1) // jobs)

    records: dict[str, dict[str, Any]] = {}
    todo: list[tuple[BatchCase, dict]] = []
    for c in cases:
        fp = _fingerprint(c, {**options, "html": html})
        old = None if force else _previous(c, out, fp)
        if old is not None:
            records[c.id] = {**old, "status": "skipped", "previous_status": old["status"]}
        else:
            records[c.id] = {"case": c.id, "status": "pending", "run_a": str(c.run_a or ""),
                             "run_b": str(c.run_b or ""), "out": str(out / c.id)}
            todo.append((c, {**options, "html": html, "threads": threads, "fingerprint": fp}))
    order = [c.id for c in cases]
    meta = {"source": str(source) if isinstance(source, (str, os.PathLike)) else "cases",
            "out": str(out), "jobs": jobs, "scheduler": None if scheduler is None else str(scheduler),
            "options": options}

    bar = None
    if progress and todo:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(todo), desc="cases", unit="case")

    def done(rec: dict[str, Any]) -> None:
        records[rec["case"]] = rec
        _write_summary(out, [records[i] for i in order], meta)
        if bar is not None:
            bar.update(1)
            bar.set_postfix_str(f"{rec['case']}: {rec['status']}")

    _write_summary(out, [records[i] for i in order], meta)
    try:
        if todo and scheduler is not None:
            _run_dask(todo, out, scheduler, done)
        elif todo:
            _run_pool(todo, out, jobs, threads, done)
    finally:
        if bar is not None:
            bar.close()
    result = [records[i] for i in order]
    counts = {s: sum(r["status"] == s for r in result) for s in (*STATUSES, "pending")}
    seconds = time.perf_counter() - t0
    _write_summary(out, result, {**meta, "seconds": round(seconds, 2), "counts": counts})
    return BatchResult(result, out, seconds, counts)

