"""Batch conversion: case discovery, manifests, parallel runs, resuming, failures kept apart, Dask."""

from __future__ import annotations

import csv
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

import vesselcad as vc
from vesselcad.batch import _run_pool, find_cases, run_batch
from vesselcad.cli import main
from vesselcad.phantom import generate_case, write_case

# Five small phantom cases (both anatomies that differ most, two view pairs) and one whose
# run B is a truncated DICOM file.
GOOD = [(1, "rca"), (4, "rca"), (2, "lca"), (5, "cs"), (7, "rca")]


@pytest.fixture(scope="module")
def archive(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("archive")
    for i, (seed, anatomy) in enumerate(GOOD):
        write_case(generate_case(seed, anatomy, 8, rows=256, cols=256), root / f"case{i}")
    broken = root / "broken"
    broken.mkdir()
    shutil.copy(root / "case0" / "run_a.dcm", broken / "run_a.dcm")
    data = (root / "case0" / "run_b.dcm").read_bytes()
    (broken / "run_b.dcm").write_bytes(data[: len(data) // 3])
    return root


def _summary(out: Path) -> dict[str, dict]:
    with (out / "summary.csv").open() as fh:
        return {r["case"]: r for r in csv.DictReader(fh)}


def test_cli_batch_finishes_good_cases_reports_broken_and_resumes(archive, tmp_path, capsys):
    out = tmp_path / "out"
    rc = main(["batch", str(archive), "--out", str(out), "--jobs", "2", "--quiet"])
    assert rc == 4  # some case failed; the others are done
    rows = _summary(out)
    assert sorted(rows) == ["broken", "case0", "case1", "case2", "case3", "case4"]
    assert rows["broken"]["status"] == "error"
    assert "run_b.dcm" in rows["broken"]["message"] and "truncated" in rows["broken"]["message"].lower()
    for i in range(len(GOOD)):
        r = rows[f"case{i}"]
        assert r["status"] == "ok", r
        d = out / f"case{i}"
        for name in ("tree.step", "tree.stl", "tree.glb", "centrelines.json", "report.json", "report.html"):
            assert (d / name).stat().st_size > 0, (i, name)
        rep = json.loads((d / "report.json").read_text())
        assert (rep["frame_a"], rep["frame_b"]) == (int(r["frame_a"]), int(r["frame_b"]))
        assert 0 <= rep["frame_a"] < 8 and 0 <= rep["frame_b"] < 8
        assert int(r["branches_ok"]) >= 1 and r["solid_valid"] == "True" and r["solid_watertight"] == "True"
        share = rep["solid"]["tree_share"]
        assert float(r["solid_tree_share"]) == share and 0.0 < share <= 1.0
        # every written tree lies in the phantom's heart-sized region around the isocentre
        tree = json.loads((d / "centrelines.json").read_text())
        pts = np.concatenate([b["points"] for b in tree["branches"]])
        assert np.linalg.norm(pts, axis=1).max() < 100.0
    js = json.loads((out / "summary.json").read_text())
    assert js["counts"]["ok"] == 5 and js["counts"]["error"] == 1 and js["jobs"] == 2
    assert js["cases"][0]["case"] == "broken" and js["cases"][0]["error_type"] == "DicomError"

    # Second run: finished cases are skipped (their records kept), the failed one is retried.
    before = {i: (out / f"case{i}" / "tree.step").stat().st_mtime_ns for i in range(len(GOOD))}
    rc = main(["batch", str(archive), "--out", str(out), "--jobs", "2", "--json"])
    assert rc == 4
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert printed["counts"]["skipped"] == 5 and printed["counts"]["error"] == 1
    assert [f["case"] for f in printed["failed"]] == ["broken"]
    assert {i: (out / f"case{i}" / "tree.step").stat().st_mtime_ns for i in range(len(GOOD))} == before
    rows = _summary(out)
    assert rows["case3"]["status"] == "skipped" and rows["case3"]["branches_ok"]  # numbers kept

    # A changed input is not "finished": touching run A of case1 re-runs only case1
    # (run_batch's defaults are the CLI's, so the options match).
    p = archive / "case1" / "run_a.dcm"
    os.utime(p, ns=(p.stat().st_atime_ns, p.stat().st_mtime_ns + 10**9))
    res = run_batch(archive, out, jobs=2)
    assert (res.counts["ok"], res.counts["skipped"], res.counts["error"]) == (1, 4, 1)
    assert {r["case"] for r in res.cases if r["status"] == "ok"} == {"case1"}


def test_force_reruns_and_manifest(archive, tmp_path):
    manifest = tmp_path / "cases.csv"
    rel = os.path.relpath(archive, tmp_path)
    sid = vc.load_run(archive / "case1" / "run_a.dcm").view.sid_mm
    geo = json.dumps({"sid_mm": sid})  # the file's own SID: a no-op override, as inline JSON
    manifest.write_text(
        "Case,run_a,run_b,geometry,frame_a,frame_b\n"
        f"first,{rel}/case1/run_a.dcm,{rel}/case1/run_b.dcm,\"{geo.replace(chr(34), chr(34) * 2)}\",2,5\n"
        f"missing,{rel}/case1/run_a.dcm,{rel}/nowhere/run_b.dcm,,,\n")
    cases = find_cases(manifest)
    assert [c.id for c in cases] == ["first", "missing"]
    assert cases[0].frames == (2, 5) and cases[0].geometry_a == {"sid_mm": sid}
    assert cases[0].run_a == tmp_path / rel / "case1" / "run_a.dcm"
    out = tmp_path / "out"
    res = run_batch(manifest, out, solid=False, html=False)
    by = {r["case"]: r for r in res.cases}
    assert by["first"]["status"] == "ok" and (by["first"]["frame_a"], by["first"]["frame_b"]) == (2, 5)
    assert by["missing"]["status"] == "error" and "nowhere" in by["missing"]["message"]
    assert not res.ok and [r["case"] for r in res.failed] == ["missing"]
    t_first = json.loads((out / "first" / "case.json").read_text())["seconds"]
    again = run_batch(manifest, out, solid=False, html=False)
    assert {r["case"]: r["status"] for r in again.cases} == {"first": "skipped", "missing": "error"}
    forced = run_batch(manifest, out, solid=False, html=False, force=True)
    assert {r["case"]: r["status"] for r in forced.cases} == {"first": "ok", "missing": "error"}
    assert json.loads((out / "first" / "case.json").read_text())["seconds"] != t_first


def test_find_cases_folder_rules(archive, tmp_path):
    root = tmp_path / "in"
    a = root / "p01"
    a.mkdir(parents=True)
    shutil.copy(archive / "case0" / "run_a.dcm", a / "IM0001")  # PACS export: no suffix, DICM preamble
    shutil.copy(archive / "case0" / "run_b.dcm", a / "IM0002")
    (a / "notes.txt").write_text("not a run")
    (a / "geometry.json").write_text(json.dumps({"sid_mm": 1100.0}))
    (a / "geometry_b.json").write_text(json.dumps({"sid_mm": 1000.0}))
    three = root / "p02"
    three.mkdir()
    for n in ("x.dcm", "y.dcm", "z.dcm"):
        shutil.copy(archive / "case0" / "run_a.dcm", three / n)
    (root / ".cache").mkdir()
    cases = find_cases(root)
    assert [c.id for c in cases] == ["p01", "p02"]
    assert (cases[0].run_a.name, cases[0].run_b.name) == ("IM0001", "IM0002")
    assert cases[0].geometry_a == a / "geometry.json" and cases[0].geometry_b == a / "geometry_b.json"
    assert cases[0].problem is None
    assert cases[1].problem and "found 3" in cases[1].problem and "manifest" in cases[1].problem


def test_bad_batch_inputs(tmp_path, archive):
    with pytest.raises(vc.InputFileError, match="nowhere"):
        find_cases(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(vc.InputFileError, match="no case folders"):
        find_cases(tmp_path / "empty")
    m = tmp_path / "m.csv"
    for text, message in (("id,run_a\nx,a.dcm\n", "run_b"),
                          ("id,run_a,run_b\nx,a.dcm,b.dcm\nx,c.dcm,d.dcm\n", "'x' appears twice"),
                          ("id,run_a,run_b\n../evil,a.dcm,b.dcm\n", "folder name"),
                          ("id,run_a,run_b,geometry_a\nx,a.dcm,b.dcm,{oops\n", "line 2.*geometry_a")):
        m.write_text(text)
        with pytest.raises(vc.ArgumentError, match=message):
            find_cases(m)
    with pytest.raises(vc.ArgumentError, match="jobs"):
        run_batch(archive, tmp_path / "o", jobs=0)
    with pytest.raises(vc.ArgumentError, match="labels"):
        run_batch(archive, tmp_path / "o", labels=None)
    with pytest.raises(vc.InputFileError, match="int9: no such segmentation model"):
        run_batch(archive, tmp_path / "o", model="int9")  # not a bundled name ('fp32', 'int8'): a path
    assert main(["batch", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o")]) == 2


def _crash_on_case_named_crash(case, out, options):
    """A worker function that dies like a segfault in native code for one case."""
    if case.id == "crash":
        os._exit(139)
    from vesselcad.batch import process_case

    return process_case(case, out, options)


def test_a_crashing_worker_loses_only_its_case(tmp_path):
    from vesselcad.batch import BatchCase

    cases = [BatchCase(n, tmp_path / f"{n}_a.dcm", tmp_path / f"{n}_b.dcm") for n in ("one", "crash", "two")]
    got = []
    todo = [(c, {"html": False, "threads": 1, "fingerprint": "f"}) for c in cases]
    _run_pool(todo, tmp_path, 2, 1, got.append, fn=_crash_on_case_named_crash)
    by = {r["case"]: r for r in got}
    assert sorted(by) == ["crash", "one", "two"]  # every case has exactly one record
    assert len(got) == 3
    assert by["crash"]["status"] == "error" and "worker process died" in by["crash"]["message"]
    # the other two ran to their own end (their inputs do not exist: a clear input error)
    assert by["one"]["status"] == "error" and by["one"]["error_type"] == "InputFileError"
    assert by["two"]["error_type"] == "InputFileError"


def test_batch_on_a_dask_local_cluster(archive, tmp_path):
    distributed = pytest.importorskip("distributed")
    manifest = tmp_path / "two.csv"
    manifest.write_text("case,run_a,run_b\n"
                        f"a,{archive}/case1/run_a.dcm,{archive}/case1/run_b.dcm\n"
                        f"b,{archive}/broken/run_a.dcm,{archive}/broken/run_b.dcm\n")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        out = tmp_path / "out"
        rc = main(["batch", str(manifest), "--out", str(out), "--scheduler", cluster.scheduler_address,
                   "--no-solid", "--no-html", "--quiet"])
    assert rc == 4
    rows = _summary(out)
    assert rows["a"]["status"] == "ok" and int(rows["a"]["branches_ok"]) >= 1
    assert (out / "a" / "centrelines.json").is_file() and not (out / "a" / "tree.step").exists()
    assert rows["b"]["status"] == "error" and "truncated" in rows["b"]["message"].lower()
    assert json.loads((out / "summary.json").read_text())["scheduler"] == cluster.scheduler_address
    assert main(["batch", str(manifest), "--out", str(out), "--scheduler", "tcp://127.0.0.1:1",
                 "--quiet"]) == 2


def test_batch_defaults_are_reconstructs_own():
    # a case's fingerprint leaves out options at their defaults: those must be reconstruct()'s
    import inspect

    from vesselcad.batch import _DEFAULTS
    from vesselcad.pipeline import reconstruct

    params = inspect.signature(reconstruct).parameters
    assert {k: params[k].default for k in _DEFAULTS} == _DEFAULTS
