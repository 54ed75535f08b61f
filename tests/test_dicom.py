"""DICOM XA reading and writing, on generated runs and on real files."""

import json
import math
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pydicom
import pytest

import vesselcad as vc

DATA = Path(__file__).parent / "data" / "dicom"
CINE = DATA / "xa_catheter_12frames_jpeg_lossless.dcm"
WG04 = DATA / "wg04_xa1"
GEOM = {"sid_mm": 1100.0, "sod_mm": 750.0, "pixel_spacing_mm": (0.3, 0.3)}


def make_run(n=5, rows=64, cols=80, dtype=np.uint8, bits=8):
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 1 << bits, (n, rows, cols)).astype(dtype)
    view = vc.CArmView(primary_deg=-30.5, secondary_deg=20.25, sid_mm=1050.0, sod_mm=765.5,
                       pixel_spacing_mm=(0.278, 0.3), rows=rows, cols=cols)
    return vc.XARun(frames=frames, view=view, frame_times_ms=np.arange(n) * 66.5, bits_stored=bits,
                    r_wave_frames=np.array([1, 4]), patient_id="P-1", patient_name="Doe^Jane",
                    study_date="20260102")


@pytest.mark.parametrize("dtype,bits,compress", [(np.uint8, 8, False), (np.uint16, 12, False),
                                                 (np.uint8, 8, True)])
def test_save_load_round_trip(tmp_path, dtype, bits, compress):
    run = make_run(dtype=dtype, bits=bits)
    path = vc.save_run(run, tmp_path / "run.dcm", compress=compress)
    back = vc.load_run(path)
    np.testing.assert_array_equal(back.frames, run.frames)
    assert back.frames.dtype == dtype and back.bits_stored == bits
    assert back.view == run.view
    np.testing.assert_allclose(back.frame_times_ms, run.frame_times_ms)
    np.testing.assert_array_equal(back.r_wave_frames, [1, 4])
    assert (back.patient_id, back.patient_name, back.study_date) == ("P-1", "Doe^Jane", "20260102")
    ds = pydicom.dcmread(path)
    assert ds.SOPClassUID == "1.2.840.10008.5.1.4.1.1.12.1" and ds.Modality == "XA"
    assert int(ds.NumberOfFrames) == 5 and ds.FrameIncrementPointer == 0x00181063
    # Same run, same bytes (deterministic UIDs).
    vc.save_run(run, tmp_path / "again.dcm", compress=compress)
    assert (tmp_path / "again.dcm").read_bytes() == path.read_bytes()


def test_irregular_frame_times_use_frame_time_vector(tmp_path):
    run = make_run()
    run.frame_times_ms = np.array([0.0, 30.0, 70.0, 100.0, 150.0])
    back = vc.load_run(vc.save_run(run, tmp_path / "r.dcm"))
    np.testing.assert_allclose(back.frame_times_ms, run.frame_times_ms)


def _without(tmp_path, keyword):
    path = vc.save_run(make_run(), tmp_path / "full.dcm")
    ds = pydicom.dcmread(path)
    delattr(ds, keyword)
    out = tmp_path / f"no_{keyword}.dcm"
    ds.save_as(out)
    return out


def test_missing_sod_names_the_tag_and_geometry_fills_it(tmp_path):
    path = _without(tmp_path, "DistanceSourceToPatient")
    with pytest.raises(vc.MissingGeometryError, match=r"DistanceSourceToPatient \(0018,1111\)") as ei:
        vc.load_run(path)
    assert ei.value.missing == ["sod_mm"]
    assert "geometry=" in str(ei.value) and str(path) in str(ei.value)
    run = vc.load_run(path, geometry={"sod_mm": 765.5})
    assert run.view.sod_mm == 765.5
    view_json = tmp_path / "view.json"
    view_json.write_text(json.dumps({"sod_mm": 700.0}))
    assert vc.load_run(path, geometry=view_json).view.sod_mm == 700.0


def test_pixel_spacing_fallback_warns(tmp_path):
    path = _without(tmp_path, "ImagerPixelSpacing")
    ds = pydicom.dcmread(path)
    ds.PixelSpacing = ["0.25", "0.25"]
    ds.save_as(path)
    with pytest.warns(vc.VesselcadWarning, match=r"PixelSpacing \(0028,0030\)"):
        run = vc.load_run(path)
    assert run.view.pixel_spacing_mm == (0.25, 0.25)


def test_bad_geometry_argument(tmp_path):
    path = vc.save_run(make_run(), tmp_path / "r.dcm")
    with pytest.raises(vc.ArgumentError, match="unknown entries"):
        vc.load_run(path, geometry={"sdd": 1000})
    with pytest.raises(vc.DicomError, match="0018,1111"):
        vc.load_run(path, geometry={"sod_mm": 2000.0})


def test_not_xa(tmp_path):
    path = vc.save_run(make_run(), tmp_path / "r.dcm")
    ds = pydicom.dcmread(path)
    ds.Modality = "CT"
    ds.SOPClassUID = "1.2.840.10008.5.1.4.1.1.2"
    ds.save_as(tmp_path / "ct.dcm")
    with pytest.raises(vc.DicomError, match=r"not an X-ray angiography file.*'CT'"):
        vc.load_run(tmp_path / "ct.dcm")


def test_truncated_file(tmp_path):
    data = vc.save_run(make_run(), tmp_path / "r.dcm").read_bytes()
    cut = tmp_path / "cut.dcm"
    cut.write_bytes(data[: len(data) - 5000])
    with pytest.raises(vc.DicomError, match="cut.dcm"):
        vc.load_run(cut)
    head = tmp_path / "head.dcm"
    head.write_bytes(data[:200])
    with pytest.raises(vc.DicomError, match="head.dcm"):
        vc.load_run(head)


def test_not_dicom_and_missing(tmp_path):
    txt = tmp_path / "notes.dcm"
    txt.write_text("this is not DICOM\n" * 20)
    with pytest.raises(vc.DicomError, match="not a DICOM file"):
        vc.load_run(txt)
    with pytest.raises(vc.InputFileError, match="no such file"):
        vc.load_run(tmp_path / "absent.dcm")
    empty = tmp_path / "empty.dcm"
    empty.write_bytes(b"")
    with pytest.raises(vc.DicomError):
        vc.load_run(empty)


def test_zero_frames(tmp_path):
    path = vc.save_run(make_run(), tmp_path / "r.dcm")
    ds = pydicom.dcmread(path)
    ds.NumberOfFrames = 0
    ds.PixelData = b""
    ds.save_as(tmp_path / "zero.dcm")
    with pytest.raises(vc.DicomError, match="0028,0008"):
        vc.load_run(tmp_path / "zero.dcm")


def test_real_catheter_cine_with_geometry():
    with pytest.raises(vc.MissingGeometryError) as ei:
        vc.load_run(CINE)
    for tag in ("(0018,1110)", "(0018,1111)", "(0018,1164)"):
        assert tag in str(ei.value)
    run = vc.load_run(CINE, geometry=GEOM)
    assert run.frames.shape == (12, 512, 512) and run.frames.dtype == np.uint8
    np.testing.assert_allclose(run.frame_times_ms, np.arange(12) * 33.0)
    assert (run.view.primary_deg, run.view.secondary_deg) == (77.0, -45.0)
    a, b = math.radians(77), math.radians(-45)
    want = [math.sin(a) * math.cos(b), -math.cos(a) * math.cos(b), math.sin(b)]
    np.testing.assert_allclose(run.view.detector_direction, want, atol=1e-12)
    # Frames are real angiograms: not blank, not saturated.
    assert 20 < run.frames.mean() < 235 and run.frames.std() > 10


def test_wg04_encodings_decode_to_the_same_image():
    ref = vc.load_run(WG04 / "XA1_UNC.dcm", geometry=dict(GEOM, primary_deg=0, secondary_deg=0)).frames
    assert ref.shape == (1, 1024, 1024) and ref.dtype == np.uint16 and ref.max() < 1024
    for name in ("RLE", "JPLL", "JLSL", "J2KR"):
        got = vc.load_run(WG04 / f"XA1_{name}.dcm", geometry=dict(GEOM, primary_deg=0, secondary_deg=0))
        np.testing.assert_array_equal(got.frames, ref, err_msg=name)
    for name, max_abs in (("JLSN", 10), ("J2KI", 30), ("JPLY", 150)):
        got = vc.load_run(WG04 / f"XA1_{name}.dcm", geometry=dict(GEOM, primary_deg=0, secondary_deg=0))
        diff = np.abs(got.frames.astype(int) - ref)
        assert diff.max() <= max_abs and diff.mean() < 3.0, name


def test_missing_decoder_says_what_to_install(monkeypatch):
    def fail(self):
        raise RuntimeError("Unable to decode as exceptions were raised by all available plugins")

    monkeypatch.setattr(pydicom.dataset.Dataset, "pixel_array", property(fail))
    with pytest.raises(vc.DecoderError, match="python-gdcm"):
        vc.load_run(WG04 / "XA1_JLSL.dcm", geometry=dict(GEOM, primary_deg=0, secondary_deg=0))


def test_frames_folder(tmp_path):
    rng = np.random.default_rng(5)
    frames = rng.integers(0, 255, (11, 40, 50), dtype=np.uint8)
    for i, f in enumerate(frames):  # natural order: frame_2 before frame_10
        cv2.imwrite(str(tmp_path / f"frame_{i}.png"), f)
    with pytest.raises(vc.InputFileError, match="missing CArmView entries"):
        vc.load_run(tmp_path)
    (tmp_path / "view.json").write_text(json.dumps(
        {"primary_deg": 30, "secondary_deg": 0, "sid_mm": 1100, "sod_mm": 750,
         "pixel_spacing_mm": [0.3, 0.3], "frame_time_ms": 40}))
    run = vc.load_run(tmp_path)
    np.testing.assert_array_equal(run.frames, frames)
    assert (run.view.rows, run.view.cols) == (40, 50)
    np.testing.assert_allclose(run.frame_times_ms, np.arange(11) * 40.0)
    cv2.imwrite(str(tmp_path / "frame_99.png"), np.zeros((10, 10), np.uint8))
    with pytest.raises(vc.InputFileError, match="frame_99.png"):
        vc.load_run(tmp_path)


def test_xarun_validates():
    view = vc.CArmView(primary_deg=0, secondary_deg=0, sid_mm=1100, sod_mm=750,
                       pixel_spacing_mm=(0.3, 0.3), rows=8, cols=8)
    with pytest.raises(vc.ArgumentError, match="frames"):
        vc.XARun(frames=np.zeros((2, 9, 8), np.uint8), view=view, frame_times_ms=[0, 1])
    with pytest.raises(vc.ArgumentError, match="frame_times_ms"):
        vc.XARun(frames=np.zeros((2, 8, 8), np.uint8), view=view, frame_times_ms=[0])
    with pytest.raises(vc.ArgumentError, match="frames"):
        vc.XARun(frames=np.zeros((2, 8, 8), np.float32), view=view, frame_times_ms=[0, 1])


def test_cli_info_on_the_real_cine(tmp_path, capsys):
    from vesselcad.cli import main

    assert main(["info", str(CINE)]) == 2
    err = capsys.readouterr().err
    assert "DistanceSourceToPatient (0018,1111)" in err and "--geometry" in err
    view_json = tmp_path / "view.json"
    view_json.write_text(json.dumps({"sid_mm": 1100, "sod_mm": 750, "pixel_spacing_mm": [0.3, 0.3]}))
    assert main(["info", str(CINE), "--geometry", str(view_json), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["frames"] == 12 and info["frame_time_ms"] == 33.0
    assert info["view"]["primary_deg"] == 77.0 and info["view"]["sod_mm"] == 750
    assert info["mm_per_px_isocentre"][0] == pytest.approx(0.3 * 750 / 1100, abs=1e-6)


@pytest.mark.skipif(shutil.which("dciodvfy") is None, reason="dicom3tools' dciodvfy not installed")
@pytest.mark.parametrize("variant", ["plain", "rle", "frame_time_vector", "12bit"])
def test_written_files_pass_the_dicom3tools_iod_verifier(tmp_path, variant):
    run = make_run(dtype=np.uint16, bits=12) if variant == "12bit" else make_run()
    if variant == "frame_time_vector":
        run.frame_times_ms = np.array([0.0, 30.0, 70.0, 100.0, 150.0])
    path = vc.save_run(run, tmp_path / "r.dcm", compress=variant == "rle")
    out = subprocess.run(["dciodvfy", str(path)], capture_output=True, text=True)
    report = (out.stdout + out.stderr).splitlines()
    assert "XAImage" in report
    problems = [line for line in report if line.startswith(("Error", "Warning")) and "DICOMDIR" not in line]
    assert problems == []


def test_view_from_a_pydicom_dataset(tmp_path):
    run = make_run()
    path = vc.save_run(run, tmp_path / "r.dcm")
    assert vc.CArmView.from_dicom(pydicom.dcmread(path)) == run.view
    ds = pydicom.dcmread(CINE, stop_before_pixels=True)
    view = vc.CArmView.from_dicom(ds, geometry=GEOM)
    assert (view.primary_deg, view.secondary_deg, view.rows, view.cols) == (77.0, -45.0, 512, 512)
