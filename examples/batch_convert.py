"""Convert an archive of two-run cases in parallel, resumably, and read the summary.

    python examples/batch_convert.py ARCHIVE --out converted --jobs 2
    python examples/batch_convert.py ARCHIVE --out converted --scheduler tcp://host:8786  # Dask cluster

ARCHIVE is a folder of case folders (two DICOM files each) or a CSV manifest
(case,run_a,run_b[,geometry_a,geometry_b,frame_a,frame_b]). Without ARCHIVE it
builds a small demo archive of phantom cases, one with a truncated file, so
you can see how a failure is reported while the other cases finish.
"""

from __future__ import annotations

import argparse
import csv
import shutil
from pathlib import Path

import vesselcad as vc


def demo_archive(root: Path) -> Path:
    from vesselcad.phantom import generate_case, write_case

    for i, (seed, anatomy) in enumerate([(1, "rca"), (2, "lca"), (5, "cs")]):
        if not (root / f"case{i}").exists():
            write_case(generate_case(seed, anatomy, 8, rows=256, cols=256), root / f"case{i}")
    broken = root / "broken"
    broken.mkdir(exist_ok=True)
    shutil.copy(root / "case0" / "run_a.dcm", broken / "run_a.dcm")
    data = (root / "case0" / "run_b.dcm").read_bytes()
    (broken / "run_b.dcm").write_bytes(data[: len(data) // 3])   # a transfer cut short
    return root


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("archive", nargs="?", type=Path)
    ap.add_argument("--out", type=Path, default=Path("converted"))
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--scheduler", help="Dask distributed scheduler address")
    ap.add_argument("--force", action="store_true")
    args = ap.parse_args()
    archive = args.archive or demo_archive(Path("demo-archive"))

    for case in vc.find_cases(archive):                  # what will run, before running it
        note = f"  PROBLEM: {case.problem}" if case.problem else ""
        print(f"{case.id}: {case.run_a} + {case.run_b}{note}")

    res = vc.run_batch(archive, args.out, jobs=args.jobs, scheduler=args.scheduler, force=args.force,
                       progress=True)
    print(res)
    for r in res.failed:
        print(f"FAILED {r['case']} ({r['status']}): {r['message']}")

    # summary.csv is what a lab loads into a spreadsheet or pandas
    with (args.out / "summary.csv").open() as fh:
        for row in csv.DictReader(fh):
            if row["status"] in ("ok", "skipped") and row["reprojection_mean_mm"]:
                print(f"{row['case']}: {row['branches_ok']}/{row['branches_total']} branches, "
                      f"{float(row['reprojection_mean_mm']):.2f} mm mean reprojection, "
                      f"{row['seconds']} s")


if __name__ == "__main__":
    main()
