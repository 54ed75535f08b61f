"""OCCT's general fuse in a separate process, so that it can be given a time limit.

OCCT's booleans cannot be interrupted from Python (OCP has no Python subclass of
``Message_ProgressIndicator``), and a few unions of real-shaped trees take OCCT
minutes. :class:`FuseWorker` runs the fuse in a long-lived helper process
(this file run by the same Python: a fresh interpreter that imports only OCP,
so OCCT's thread pool works there as in the caller), talks to it by one JSON line per job
and binary BRep files (``BinTools``: exact), and kills it when a job overruns;
the next job starts a new one. The face history the caller needs (which faces
of the result each input face became) comes back as face indices and is
replayed by :class:`MappedFuse`, which answers ``IsDeleted``/``Modified``
like ``BRepAlgoAPI_Fuse``.

The same helper integrates a solid's volume without the caller waiting for it
(:meth:`FuseWorker.volume`): OCP holds the GIL through OCCT's calls, so a thread
could not overlap the integration with the caller's next steps (the pictures and
the triangulation of ``Reconstruction.write``); a second process can.
"""

from __future__ import annotations

import atexit
import contextlib
import json
import os
import queue
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from OCP.BinTools import BinTools
from OCP.BRep import BRep_Builder
from OCP.TopAbs import TopAbs_FACE
from OCP.TopExp import TopExp
from OCP.TopoDS import TopoDS_Compound, TopoDS_Iterator, TopoDS_Shape
from OCP.TopTools import TopTools_IndexedMapOfShape

__all__ = ["FuseWorker", "MappedFuse"]

#: Seconds the helper process may take to start (import OCP) before it counts as unable to run.
STARTUP_TIMEOUT_S = 60.0


def _is_python(executable: str | None) -> bool:
    """Whether ``executable`` names a Python interpreter (python, python3.11, python.exe, pypy3)."""
    return bool(executable) and re.fullmatch(r"(python|pypy)[\d.]*(w)?(\.exe)?",
                                             os.path.basename(executable).lower()) is not None


def _faces(shape: TopoDS_Shape) -> TopTools_IndexedMapOfShape:
    m = TopTools_IndexedMapOfShape()
    TopExp.MapShapes_s(shape, TopAbs_FACE, m)
    return m


def _write_shapes(shapes: list[TopoDS_Shape], path: str) -> None:
    comp = TopoDS_Compound()
    builder = BRep_Builder()
    builder.MakeCompound(comp)
    for s in shapes:
        builder.Add(comp, s)
    BinTools.Write_s(comp, path)


def _read_shape(path: str) -> TopoDS_Shape:
    shape = TopoDS_Shape()
    BinTools.Read_s(shape, path)
    return shape


def _children(shape: TopoDS_Shape) -> list[TopoDS_Shape]:
    it = TopoDS_Iterator(shape)
    out = []
    while it.More():
        out.append(it.Value())
        it.Next()
    return out


class MappedFuse:
    """A fuse's result and face history, replayed on the caller's own input shapes.

    Parameters
    ----------
    inputs : list of TopoDS_Shape
        The shapes that went into the fuse (this process's objects).
    result : TopoDS_Shape
        The result, as read back.
    images : list of list of list of int
        For input ``k`` and its ``j``-th face (``TopExp.MapShapes`` order), the
        1-based indices of the result faces it became (empty: deleted).
    """

    def __init__(self, inputs: list[TopoDS_Shape], result: TopoDS_Shape, images: list[list[list[int]]]):
        self._result = result
        rmap = _faces(result)
        faces = [rmap.FindKey(i) for i in range(1, rmap.Extent() + 1)]
        self._maps = [_faces(s) for s in inputs]
        self._images = [[[faces[i - 1] for i in img] for img in per] for per in images]

    def _lookup(self, face: TopoDS_Shape) -> list[TopoDS_Shape] | None:
        for m, per in zip(self._maps, self._images, strict=True):
            j = m.FindIndex(face)
            if j > 0:
                return per[j - 1]
        return None

    def Shape(self) -> TopoDS_Shape:  # noqa: N802 - OCCT's name
        return self._result

    def IsDeleted(self, face: TopoDS_Shape) -> bool:  # noqa: N802
        img = self._lookup(face)
        return img is not None and not img

    def Modified(self, face: TopoDS_Shape) -> list[TopoDS_Shape]:  # noqa: N802
        return list(self._lookup(face) or [])


class _Later:
    """The answer of a job the caller did not wait for (:meth:`FuseWorker.volume`)."""

    def __init__(self, worker: FuseWorker, file: str, deadline: float) -> None:
        self.worker, self.file, self.deadline = worker, file, deadline
        self.value: float | None = None

    def __call__(self) -> float | None:
        """Wait for the answer (until the job's deadline); None if the helper gave none."""
        with self.worker._lock:
            if self.worker._later is self:
                self.worker._settle()
        return self.value


class FuseWorker:
    """A helper process that runs general fuses with a time limit.

    ``fuse(shapes, fuzzy, parallel, timeout_s)`` returns a :class:`MappedFuse`,
    ``None`` when OCCT reports failure, or raises :class:`TimeoutError` when the
    job overran (the helper is then killed) and :class:`OSError` when the helper
    cannot run here (the caller then fuses in its own process).
    ``volume(shape, eps, timeout_s)`` starts a volume integration and returns at
    once with a function that waits for its result.
    """

    def __init__(self) -> None:
        self._pid = os.getpid()
        self._proc: subprocess.Popen | None = None
        self._lines: queue.Queue[str | None] = queue.Queue()
        self._ready = False
        self._dir = tempfile.mkdtemp(prefix="vesselcad-fuse-")
        self._lock = threading.Lock()
        self._pump: threading.Thread | None = None  # the thread reading the helper's output
        self._later: _Later | None = None  # a job whose answer nobody has read yet
        atexit.register(self.close)

    def close(self) -> None:
        """Stop the helper and remove its folder (at exit; a forked copy leaves both alone)."""
        if os.getpid() != self._pid:
            return
        self.stop()
        shutil.rmtree(self._dir, ignore_errors=True)

    def _start(self) -> subprocess.Popen:
        if self._proc is not None and self._proc.poll() is None:
            return self._proc
        if not _is_python(sys.executable) or getattr(sys, "frozen", False):
            # embedded in an application (CQ-editor, FreeCAD): sys.executable would start the application
            raise OSError(f"{sys.executable!r} is not a Python interpreter: no helper process")
        # run as a script: it imports OCP only (about 1 s), not this package
        self._proc = subprocess.Popen(
            [sys.executable, "-P", str(Path(__file__).resolve())], stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, bufsize=1)
        self._lines = queue.Queue()
        self._ready = False
        out, lines = self._proc.stdout, self._lines

        def pump() -> None:
            for line in out:
                lines.put(line)
            lines.put(None)

        self._pump = threading.Thread(target=pump, daemon=True)
        self._pump.start()
        return self._proc

    def start(self) -> None:
        """Start the helper now (it takes about a second to import OCCT), if not running."""
        if os.getpid() != self._pid:
            # a forked copy of the process that started the helper: leave that one (and its
            # folder) to its owner, start our own
            self.__init__()
        with self._lock:
            self._start()

    def stop(self) -> None:
        """Kill the helper (the next job starts a new one)."""
        proc, self._proc = self._proc, None
        if proc is None or os.getpid() != self._pid:
            return
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        # its pipes closed too (the reader thread ends at the killed helper's end of output)
        with contextlib.suppress(OSError):
            if proc.stdin is not None:
                proc.stdin.close()
        pump, self._pump = self._pump, None
        if pump is not None:
            pump.join(timeout=1.0)
            if not pump.is_alive() and proc.stdout is not None:
                proc.stdout.close()

    def _wait_ready(self) -> None:
        # the time limit of a job starts once the helper has imported OCCT
        if self._ready:
            return
        try:
            line = self._lines.get(timeout=STARTUP_TIMEOUT_S)
        except queue.Empty:
            line = None
        if line is None or line.strip() != "ready":
            raise OSError("the fuse helper process did not start")
        self._ready = True

    def fuse(self, shapes: list[TopoDS_Shape], fuzzy: float, parallel: bool, timeout_s: float
             ) -> MappedFuse | None:
        """Fuse ``shapes`` in the helper (the first the argument, the rest tools).

        Returns None when OCCT reports failure or the helper crashed on the job;
        raises TimeoutError after ``timeout_s`` (the helper is killed) and OSError
        when no helper process can be started.
        """
        if os.getpid() != self._pid:  # a forked copy (its lock may have been copied held)
            self.__init__()
        with self._lock:
            self._settle()
            src = os.path.join(self._dir, "in.bin")
            dst = os.path.join(self._dir, "out.bin")
            _write_shapes(shapes, src)
            self._send({"in": src, "out": dst, "fuzzy": fuzzy, "parallel": bool(parallel)})
            try:
                line = self._lines.get(timeout=timeout_s)
            except queue.Empty:
                self.stop()
                raise TimeoutError(f"OCCT's boolean fuse did not finish within {timeout_s:g} s") from None
            if line is None:  # OCCT crashed on these shapes
                self.stop()
                return None
            answer = json.loads(line)
            if not answer.get("done"):
                return None
            result = _read_shape(dst)
            for f in (src, dst):
                with contextlib.suppress(OSError):
                    os.remove(f)
            return MappedFuse(shapes, result, answer["images"])

    def volume(self, shape: TopoDS_Shape, eps: float, timeout_s: float) -> Callable[[], float | None] | None:
        """Start integrating ``shape``'s volume (``BRepGProp.VolumeProperties``, relative
        accuracy ``eps``, closed shells only) in the running helper and return at once.

        Returns a function that waits for the volume (mm^3; the shape arrives exact and the
        figure agrees with this process's to round-off) and gives None where the helper
        crashed, was stopped, or took longer than ``timeout_s``. The next job of this worker
        waits for it first.
        Returns None, starting nothing, where no helper is running: starting one (about a
        second) takes longer than most integrations.
        """
        if os.getpid() != self._pid:
            self.__init__()
        with self._lock:
            if self._proc is None or self._proc.poll() is not None:
                return None
            self._settle()
            src = os.path.join(self._dir, "volume.bin")
            BinTools.Write_s(shape, src)
            self._send({"in": src, "volume": float(eps)})
            self._later = _Later(self, src, time.monotonic() + float(timeout_s))
            return self._later

    def _send(self, job: dict[str, Any]) -> None:
        """Give the helper one job (the lock held), starting it if needed."""
        line = json.dumps(job) + "\n"
        for attempt in range(2):
            proc = self._start()
            try:
                self._wait_ready()
                proc.stdin.write(line)
                proc.stdin.flush()
                return
            except OSError:  # it ended since the last job: start a new one, once
                self.stop()
                if attempt:
                    raise

    def _settle(self) -> None:
        """Read the answer of the job started without waiting, if any (the lock held)."""
        later, self._later = self._later, None
        if later is None:
            return
        try:
            line = self._lines.get(timeout=max(later.deadline - time.monotonic(), 0.0))
        except queue.Empty:
            line = None
        if line is None:  # crashed on it, or still busy past its deadline
            self.stop()
        else:
            with contextlib.suppress(ValueError, TypeError):
                v = json.loads(line).get("volume")
                later.value = float(v) if v is not None else None
        with contextlib.suppress(OSError):
            os.remove(later.file)

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # pragma: no cover - interpreter shutdown
            pass


def _serve() -> None:  # pragma: no cover - runs in the helper process
    from OCP.BRepAlgoAPI import BRepAlgoAPI_Fuse
    from OCP.BRepGProp import BRepGProp
    from OCP.GProp import GProp_GProps
    from OCP.TopTools import TopTools_ListOfShape

    def as_list(shapes: list[TopoDS_Shape]) -> TopTools_ListOfShape:
        out = TopTools_ListOfShape()
        for s in shapes:
            out.Append(s)
        return out

    # answers go to the original stdout; whatever OCCT prints goes to stderr (discarded)
    answers = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)
    answers.write("ready\n")
    answers.flush()
    for line in sys.stdin:
        job = json.loads(line)
        if "volume" in job:
            props = GProp_GProps()
            BRepGProp.VolumeProperties_s(_read_shape(job["in"]), props, float(job["volume"]), True)
            answers.write(json.dumps({"volume": props.Mass()}) + "\n")
            answers.flush()
            continue
        shapes = _children(_read_shape(job["in"]))
        op = BRepAlgoAPI_Fuse()
        op.SetArguments(as_list(shapes[:1]))
        op.SetTools(as_list(shapes[1:]))
        op.SetFuzzyValue(float(job["fuzzy"]))
        op.SetRunParallel(bool(job["parallel"]))
        op.SetUseOBB(True)
        op.SetToFillHistory(True)
        op.Build()
        answer: dict[str, Any] = {"done": bool(op.IsDone())}
        if answer["done"]:
            result = op.Shape()
            rmap = _faces(result)
            images = []
            for s in shapes:
                fmap = _faces(s)
                per = []
                for j in range(1, fmap.Extent() + 1):
                    f = fmap.FindKey(j)
                    if op.IsDeleted(f):
                        per.append([])
                        continue
                    mod = list(op.Modified(f)) or [f]
                    per.append([i for i in (rmap.FindIndex(m) for m in mod) if i > 0])
                images.append(per)
            BinTools.Write_s(result, job["out"])
            answer["images"] = images
        answers.write(json.dumps(answer) + "\n")
        answers.flush()


if __name__ == "__main__":  # pragma: no cover
    _serve()
