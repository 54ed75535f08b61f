"""Outputs of a reconstruction: CAD files, centrelines, report.json, pictures and report.html.

``report.html`` is one self-contained file (no network): the two chosen frames
with their segmentation, the matched 2D pieces and the reprojected 3D
centrelines, the phase error matrix, the numbers, and an interactive 3D view of
the tree drawn by a small WebGL viewer embedded in the page (mesh data inline).
"""

from __future__ import annotations

import base64
import html
import json
import time
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import OutputError, VesselcadWarning
from .io.atomic import atomic_path, atomic_write_bytes, atomic_write_text

if TYPE_CHECKING:
    from .pipeline import Reconstruction

__all__ = ["write_outputs", "plot_overlays"]

_PALETTE = np.array([[230, 25, 75], [60, 180, 75], [255, 225, 25], [0, 130, 200], [245, 130, 48],
                     [145, 30, 180], [70, 240, 240], [240, 50, 230], [210, 245, 60], [250, 190, 212],
                     [0, 128, 128], [220, 190, 255], [170, 110, 40], [255, 250, 200], [128, 0, 0]], np.uint8)


def plot_overlays(rec: Reconstruction, path: str | Path) -> Path:
    """Both chosen frames: segmentation, 2D pieces (thin) and reprojected 3D centrelines (bold).

    Each branch has one colour in both views; a branch the solid leaves out
    (:attr:`Reconstruction.solid_left_out`) is dashed. Written atomically as PNG.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .pipeline import JOINED_NOTE
    from .segment import overlay_labels

    left_out = rec.solid_left_out  # drawn dashed: the STEP/STL/GLB do not hold them
    fig, axes = plt.subplots(1, 2, figsize=(13, 6.8), dpi=100)
    for k, ax in enumerate(axes):
        frame, lab, view = rec.frames[k], rec.labels[k], rec.views[k]
        ax.imshow(overlay_labels(frame, lab, alpha=0.25))
        for b in rec.branches:
            c = _PALETTE[b.id % len(_PALETTE)] / 255.0
            piece = b.pair.points_a_px if k == 0 else b.pair.points_b_px
            ax.plot(piece[:, 0], piece[:, 1], "-", color="white", lw=0.8, alpha=0.9)
            if b.ok:
                p = view.project(b.points_mm)
                ax.plot(p[:, 0], p[:, 1], ls=(0, (3, 2)) if b.id in left_out else "-", color=c, lw=2.0)
                ax.text(p[len(p) // 2, 0], p[len(p) // 2, 1], str(b.id), color=c, fontsize=8,
                        fontweight="bold")
                if any(w.startswith(JOINED_NOTE) for w in b.warnings):
                    # joined to another tree across a stretch the matching left unpaired: check it
                    ax.plot(*p[0], "D", color="#ff00ff", mec="black", ms=8)
            else:
                ax.plot(piece[:, 0], piece[:, 1], ":", color="red", lw=1.5)
        frame_no = rec.phase.frame_a if k == 0 else rec.phase.frame_b
        g = rec.graphs[k]
        if g.root is not None:  # where the tree starts (the ostium found in this view)
            ax.plot(*g.landmarks[g.root].point_px, "*", color="yellow", mec="black", ms=15)
        kps = rec.phase.keypoints_a if k == 0 else rec.phase.keypoints_b
        for obj, pts in kps.items():  # the stationary object's key point the phase matching used
            q = np.asarray(pts[frame_no], float)
            if np.isfinite(q).all():
                ax.plot(*q, "+", color="cyan", ms=14, mew=2)
                ax.text(q[0] + 6, q[1] - 6, obj, color="cyan", fontsize=8)
        v = rec.header_views[k]
        ax.set_title(f"run {'AB'[k]}, frame {frame_no} ({v.primary_deg:+.1f}°, {v.secondary_deg:+.1f}°)",
                     fontsize=10)
        ax.set_axis_off()
    e = rec.errors
    # two legend lines of about equal length (one of 190 characters ran past the figure's edges)
    fig.suptitle("segmentation (colours), matched 2D pieces (white), reprojected 3D centrelines (bold, "
                 "numbered; dashed: not in the solid), failed branches (red dotted),\nroot of each view "
                 "(yellow star), phase key point (cyan +), start joined to another tree across an unpaired "
                 "stretch (magenta diamond)"
                 + (f"\nreprojection {e['mean_px']:.2f} ± {e['sd_px']:.2f} px "
                    f"({e['mean_mm']:.3f} ± {e['sd_mm']:.3f} mm), max {e['max_px']:.2f} px" if e else ""),
                 fontsize=10)
    # fixed margins (tight_layout measured every text for 0.15 s a picture: docs/results.md)
    fig.subplots_adjust(left=0.005, right=0.995, bottom=0.005, top=0.86, wspace=0.01)
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path


def _tube_mesh(rec: Reconstruction) -> tuple[np.ndarray, np.ndarray]:
    """Triangles of simple tubes around the centrelines (for the 3D view when there is no solid)."""
    verts, faces, off = [], [], 0
    n_around = 12
    ang = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    for b in rec.ok_branches:
        p, r = b.points_mm, b.radius_mm
        t = np.gradient(p, axis=0)
        t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
        ref = np.where(np.abs(t[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
        n1 = np.cross(t, ref)
        n1 /= np.linalg.norm(n1, axis=1, keepdims=True)
        n2 = np.cross(t, n1)
        ring = p[:, None] + r[:, None, None] * (np.cos(ang)[None, :, None] * n1[:, None]
                                                + np.sin(ang)[None, :, None] * n2[:, None])
        m = len(p)
        i = np.arange(m - 1)[:, None]
        j = np.arange(n_around)[None, :]
        a = off + i * n_around + j
        bq = off + i * n_around + (j + 1) % n_around
        f = np.stack([a, bq, a + n_around, bq, bq + n_around, a + n_around], axis=-1).reshape(-1, 3)
        verts.append(ring.reshape(-1, 3))
        faces.append(f)
        off += m * n_around
    if not verts:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    return np.vstack(verts), np.vstack(faces)


def _mesh_for_view(rec: Reconstruction) -> tuple[np.ndarray, np.ndarray, str]:
    if rec.solid is not None:
        try:
            tm = rec.solid.to_trimesh(tolerance=0.05, angular_deflection=0.5, check_closed=False)
            return np.asarray(tm.vertices), np.asarray(tm.faces), "fused solid"
        except Exception:  # fall back to tubes; the solid's own files report its state
            pass
    v, f = _tube_mesh(rec)
    return v, f, "tubes around the centrelines (no solid)"


def _b64(a: np.ndarray, dtype: str) -> str:
    return base64.b64encode(np.ascontiguousarray(a, dtype=dtype).tobytes()).decode("ascii")


def _png_b64(path: Path) -> str:
    return base64.b64encode(path.read_bytes()).decode("ascii")


_VIEWER_JS = r"""
(function () {
  const cv = document.getElementById('view3d');
  const gl = cv.getContext('webgl');
  const status = document.getElementById('view3d-status');
  if (!gl) { status.textContent = 'WebGL is not available in this browser'; return; }
  function dec(id, T) {
    const s = atob(document.getElementById(id).textContent.trim());
    const u = new Uint8Array(s.length);
    for (let i = 0; i < s.length; i++) u[i] = s.charCodeAt(i);
    return new T(u.buffer);
  }
  const P = dec('mesh-vertices', Float32Array), F = dec('mesh-faces', Uint32Array);
  const L = dec('lines-vertices', Float32Array), LO = dec('lines-out-vertices', Float32Array);
  const nv = P.length / 3;
  let c = [0, 0, 0], lo = [1e9, 1e9, 1e9], hi = [-1e9, -1e9, -1e9];
  const all = P.length ? P : L;
  for (let i = 0; i < all.length; i += 3) for (let k = 0; k < 3; k++) {
    lo[k] = Math.min(lo[k], all[i + k]); hi[k] = Math.max(hi[k], all[i + k]); }
  for (let k = 0; k < 3; k++) c[k] = 0.5 * (lo[k] + hi[k]);
  const R = 0.5 * Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]) || 1;
  const N = new Float32Array(P.length);
  for (let i = 0; i < F.length; i += 3) {
    const a = 3 * F[i], b = 3 * F[i + 1], d = 3 * F[i + 2];
    const u = [P[b] - P[a], P[b + 1] - P[a + 1], P[b + 2] - P[a + 2]];
    const v = [P[d] - P[a], P[d + 1] - P[a + 1], P[d + 2] - P[a + 2]];
    const n = [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]];
    for (const j of [a, b, d]) for (let k = 0; k < 3; k++) N[j + k] += n[k];
  }
  function sh(type, src) { const s = gl.createShader(type); gl.shaderSource(s, src); gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s)); return s; }
  function prog(vs, fs) { const p = gl.createProgram(); gl.attachShader(p, sh(gl.VERTEX_SHADER, vs));
    gl.attachShader(p, sh(gl.FRAGMENT_SHADER, fs)); gl.linkProgram(p); return p; }
  const pm = prog('attribute vec3 p; attribute vec3 n; uniform mat4 M; uniform mat3 Q; varying vec3 vn;' +
    'void main(){ vn = Q * n; gl_Position = M * vec4(p, 1.0); }',
    'precision mediump float; varying vec3 vn; void main(){ vec3 n = normalize(vn);' +
    'float l = 0.25 + 0.75 * abs(dot(n, normalize(vec3(0.3, 0.5, 1.0))));' +
    'gl_FragColor = vec4(vec3(0.85, 0.25, 0.22) * l, 1.0); }');
  const pl = prog('attribute vec3 p; uniform mat4 M; void main(){ gl_Position = M * vec4(p, 1.0); }',
    'precision mediump float; uniform vec3 C; void main(){ gl_FragColor = vec4(C, 1.0); }');
  function attr(p, name, b) { const a = gl.getAttribLocation(p, name); gl.bindBuffer(gl.ARRAY_BUFFER, b);
    gl.enableVertexAttribArray(a); gl.vertexAttribPointer(a, 3, gl.FLOAT, false, 0, 0); return a; }
  function buf(data, target) { const b = gl.createBuffer(); gl.bindBuffer(target, b);
    gl.bufferData(target, data, gl.STATIC_DRAW); return b; }
  const bp = buf(P, gl.ARRAY_BUFFER), bn = buf(N, gl.ARRAY_BUFFER), bl = buf(L, gl.ARRAY_BUFFER);
  const blo = buf(LO, gl.ARRAY_BUFFER);
  const ext = gl.getExtension('OES_element_index_uint');
  const bf = buf(ext ? F : new Uint16Array(F), gl.ELEMENT_ARRAY_BUFFER);
  let yaw = 0.6, pitch = -0.4, zoom = 1.0, drag = null;
  cv.addEventListener('mousedown', e => { drag = [e.clientX, e.clientY]; });
  window.addEventListener('mouseup', () => { drag = null; });
  window.addEventListener('mousemove', e => { if (!drag) return;
    yaw += 0.01 * (e.clientX - drag[0]); pitch += 0.01 * (e.clientY - drag[1]);
    drag = [e.clientX, e.clientY]; draw(); });
  cv.addEventListener('wheel', e => { e.preventDefault(); zoom *= Math.exp(0.001 * e.deltaY); draw(); });
  function draw() {
    const cy = Math.cos(yaw), sy = Math.sin(yaw), cp = Math.cos(pitch), sp = Math.sin(pitch);
    // LPS: look from the patient's front (anterior, -y) with the head (+z) up.
    const rot = [cy, 0, -sy, sy * sp, cp, cy * sp, sy * cp, -sp, cy * cp];  // yaw then pitch
    const base = [1, 0, 0, 0, 0, 1, 0, -1, 0];  // x->x, z->up, -y->toward the viewer
    const Q = new Array(9).fill(0);
    for (let i = 0; i < 3; i++) for (let j = 0; j < 3; j++) for (let k = 0; k < 3; k++)
      Q[3 * i + j] += rot[3 * i + k] * base[3 * k + j];
    const s = 1.0 / (R * zoom), asp = cv.width / cv.height;
    const M = new Float32Array(16);
    for (let i = 0; i < 3; i++) {
      const sc = i === 0 ? s / asp : s, t = -(Q[3 * i] * c[0] + Q[3 * i + 1] * c[1] + Q[3 * i + 2] * c[2]);
      M[i] = Q[3 * i] * sc; M[4 + i] = Q[3 * i + 1] * sc; M[8 + i] = Q[3 * i + 2] * sc;
      M[12 + i] = t * sc;
    }
    M[2] *= -0.5; M[6] *= -0.5; M[10] *= -0.5; M[14] *= -0.5; M[15] = 1;
    const Qt = new Float32Array([Q[0], Q[3], Q[6], Q[1], Q[4], Q[7], Q[2], Q[5], Q[8]]);
    gl.viewport(0, 0, cv.width, cv.height); gl.clearColor(1, 1, 1, 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT); gl.enable(gl.DEPTH_TEST);
    if (F.length) {
      gl.useProgram(pm);
      gl.uniformMatrix4fv(gl.getUniformLocation(pm, 'M'), false, M);
      gl.uniformMatrix3fv(gl.getUniformLocation(pm, 'Q'), false, Qt);
      attr(pm, 'p', bp);
      const an = attr(pm, 'n', bn);
      gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, bf);
      gl.drawElements(gl.TRIANGLES, F.length, ext ? gl.UNSIGNED_INT : gl.UNSIGNED_SHORT, 0);
      gl.disableVertexAttribArray(an);
    }
    // centrelines the solid holds (blue) and those it leaves out (orange), over the solid
    for (const [V, b, col] of [[L, bl, [0.1, 0.2, 0.9]], [LO, blo, [0.95, 0.55, 0.05]]]) {
      if (!V.length) continue;
      gl.useProgram(pl); gl.disable(gl.DEPTH_TEST);
      gl.uniformMatrix4fv(gl.getUniformLocation(pl, 'M'), false, M);
      gl.uniform3fv(gl.getUniformLocation(pl, 'C'), col);
      attr(pl, 'p', b);
      gl.drawArrays(gl.LINES, 0, V.length / 3);
    }
  }
  draw();
  status.textContent = nv + ' vertices, ' + (F.length / 3) + ' triangles; drag to rotate, wheel to zoom';
  cv.dataset.rendered = 'true';
})();
"""


def _html(rec: Reconstruction, report: dict[str, Any], overlay_png: Path, phase_png: Path,
          verts: np.ndarray, faces: np.ndarray, mesh_kind: str) -> str:
    left_out = {b["id"] for b in report["branches"] if b["in_solid"] is False}
    lines: dict[bool, list[np.ndarray]] = {False: [], True: []}  # held, left out of the solid
    for b in rec.ok_branches:
        p = b.points_mm
        lines[b.id in left_out].append(np.stack([p[:-1], p[1:]], axis=1).reshape(-1, 3))
    lv, lo = (np.vstack(lines[k]) if lines[k] else np.zeros((0, 3)) for k in (False, True))
    e = rec.errors
    rows = []
    for b in report["branches"]:
        rp, rm = b["reprojection_px"], b["reprojection_mm"]
        length = "" if b["length_mm"] is None else f"{b['length_mm']:.1f}"
        px = "" if rp is None else f"{rp['mean']:.2f} / {rp['max']:.2f}"
        mm = "" if rm is None else f"{rm['mean']:.3f}"
        parent = "" if b["parent"] is None else str(b["parent"])
        ga, gb = b["graph_branches"]
        held = {None: "", True: "yes"}.get(b["in_solid"], f"no: {b['solid_note']}")
        rows.append(f"<tr><td>{b['id']}</td><td>{ga} / {gb}</td><td>{b['found_by']}</td><td>{parent}</td>"
                    f"<td>{length}</td>"
                    f"<td>{px}</td><td>{mm}</td><td>{html.escape(b['status'])}</td>"
                    f"<td>{html.escape(held)}</td></tr>")
    ref = report["refinement"]
    ref_txt = "off" if ref is None else (
        f"{'applied' if ref['applied'] else 'not applied'}: reconstruction error {ref['before_px']} px → "
        f"{ref['after_px']} px over {ref['landmarks']} landmark pairs and {ref['curve_points']} branch "
        "samples; "
        f"view B rotated {ref['rotation_deg']}°, isocentre shifted {ref['offset_mm']} mm"
        + ("" if not any(ref.get("keypoint_shift_mm") or ()) else
           f" ({ref['keypoint_shift_mm']} mm of it for the stationary object's key point, which disagreed by "
           f"{ref['keypoint_px'][0]} px on the files' geometry)")
        + ("" if not any(ref.get("landmark_shift_mm") or ()) else
           f" ({ref['landmark_shift_mm']} mm of it across the epipolar lines, where "
           f"{ref['landmark_counts'][1]} instead of {ref['landmark_counts'][0]} of view A's branch and end "
           "points agree with view B's)"))
    solid = report["solid"]
    solid_txt = "not built" if solid is None else (
        f"valid {solid['valid']}, watertight {solid['watertight']}, volume {solid['volume_mm3']:.1f} mm³, "
        f"holding <b>{solid['tree_share']:.0%}</b> of the reconstructed centreline length"
        + (f", left out: {html.escape(json.dumps(solid['failed']))}" if solid["failed"] else ""))
    warn = "".join(f"<li>{html.escape(w)}</li>" for w in rec.warnings) or "<li>none</li>"
    timing = ", ".join(f"{k} {v:.2f} s" for k, v in report["timings_s"].items())
    rep_txt = (f"{e['mean_px']:.2f} ± {e['sd_px']:.2f} px, max {e['max_px']:.2f} px "
               f"({e['mean_mm']:.3f} ± {e['sd_mm']:.3f} mm, max {e['max_mm']:.3f} mm)" if e else "n/a")
    ph = rec.phase
    vessel_txt = ("" if ph.consistency is None else
                  f" and the vessels' epipolar consistency ({ph.consistency[ph.frame_a, ph.frame_b]:.3f} "
                  "crossings differing per epipolar line)")
    phase_txt = f"phase error {ph.error_mm:.3f} mm, " if np.isfinite(ph.error_mm) else ""
    srcs = " and ".join(html.escape(s or "(in memory)") for s in rec.sources)
    seg = report.get("segmentation") or {}
    if seg.get("labels") == "given":
        seg_txt = "labels given to reconstruct (no model)"
    elif seg.get("labels") == "model":
        seg_txt = (f"model {html.escape(str(seg.get('model') or 'given as a Segmenter'))}"
                   f", test-time augmentation: {html.escape(str(seg.get('tta')))}"
                   f", frames labelled: {html.escape(str(seg.get('frame_search')))}")
    else:
        seg_txt = "not recorded"
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>vesselcad reconstruction</title>
<style>
body {{ font-family: system-ui, sans-serif; margin: 1.5em; color: #222; max-width: 1350px; }}
table {{ border-collapse: collapse; font-size: 0.9em; }}
td, th {{ border: 1px solid #ccc; padding: 2px 8px; }}
img {{ max-width: 100%; }} #view3d {{ border: 1px solid #aaa; cursor: grab; }}
.grid {{ display: flex; gap: 1.5em; flex-wrap: wrap; align-items: flex-start; }}
</style></head><body>
<h1>vesselcad reconstruction</h1>
<p>Runs: {srcs}. Segmentation: {seg_txt}. Chosen frames: <b>A {ph.frame_a}</b>, <b>B {ph.frame_b}</b> by
{html.escape(ph.basis)}{vessel_txt if ph.objects else ''} ({phase_txt}confidence
{ph.confidence:.2f}). Branches reconstructed: <b>{len(rec.ok_branches)} of {len(rec.branches)}</b>
matched pairs ({len(rec.graphs[0].branches)} and {len(rec.graphs[1].branches)} branches in the 2D graphs).
Reprojection error: <b>{rep_txt}</b>. Solid: {solid_txt}. Geometry refinement: {ref_txt}.</p>
<h2>Chosen frames</h2>
<img id="overlay" alt="chosen frames with segmentation and reprojected centrelines"
 src="data:image/png;base64,{_png_b64(overlay_png)}">
<div class="grid">
<div><h2>3D tree</h2>
<canvas id="view3d" width="640" height="520"></canvas>
<div id="view3d-status">loading…</div><div>Shown: {html.escape(mesh_kind)} (red), centrelines (blue; orange
where the solid leaves them out).
LPS frame, seen from the front, head up.</div></div>
<div><h2>Motion phase</h2>
<img id="phase" alt="phase error matrix" src="data:image/png;base64,{_png_b64(phase_png)}"
 width="{1120 if ph.consistency is not None else 560}"></div>
</div>
<h2>Branches</h2>
<table><tr><th>id</th><th>2D branches A / B</th><th>paired by</th><th>parent</th><th>length mm</th>
<th>reprojection px mean / max</th><th>mm mean</th><th>status</th><th>in the solid</th></tr>
{''.join(rows)}</table>
<h2>Warnings</h2><ul>{warn}</ul>
<p>Timings: {timing}. vesselcad {html.escape(report['vesselcad'])}.</p>
<script type="application/octet-stream" id="mesh-vertices">{_b64(verts, '<f4')}</script>
<script type="application/octet-stream" id="mesh-faces">{_b64(faces, '<u4')}</script>
<script type="application/octet-stream" id="lines-vertices">{_b64(lv, '<f4')}</script>
<script type="application/octet-stream" id="lines-out-vertices">{_b64(lo, '<f4')}</script>
<script>{_VIEWER_JS}</script>
</body></html>
"""


def write_outputs(rec: Reconstruction, out: Path, *, html: bool = True, progress: bool = False
                  ) -> dict[str, Path]:
    """Write every output of a reconstruction into the folder ``out`` (see :meth:`Reconstruction.write`)."""
    from .phase import plot_error_matrix

    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{out}: cannot create the output folder ({exc})") from None
    t0 = time.perf_counter()
    paths: dict[str, Path] = {}
    if rec.solid is not None:
        # the solid's volume (the STL's check, report.json) is integrated in the booleans' helper
        # process while this one draws the pictures and triangulates the solid
        rec.solid._start_volume()
    paths["overlay.png"] = plot_overlays(rec, out / "overlay.png")
    paths["phase.png"] = plot_error_matrix(rec.phase, out / "phase.png",
                                           title=f"chosen frames ({rec.phase.frame_a}, {rec.phase.frame_b})")
    if rec.tree is not None:
        paths["centrelines.json"] = out / "centrelines.json"
        rec.tree.to_json(paths["centrelines.json"])
        paths["centrelines.vtp"] = out / "centrelines.vtp"
        rec.tree.to_vtp(paths["centrelines.vtp"])
    if rec.solid is not None:
        for name, fn in (("tree.step", rec.solid.export_step), ("tree.stl", rec.solid.export_stl),
                         ("tree.glb", rec.solid.export_glb)):
            try:
                with warnings.catch_warnings(record=True) as seen:
                    warnings.simplefilter("always")
                    fn(out / name)
                paths[name] = out / name
            except Exception as exc:  # one output never loses the others
                rec.warnings.append(f"{name}: could not be written ({type(exc).__name__}: {exc})")
            # what an export says about its file (a mesh with holes, or not manifold somewhere)
            # goes into report.json too, and on to the caller as before
            for w in seen:
                if issubclass(w.category, VesselcadWarning):
                    note = f"{name}: {w.message}"
                    if note not in rec.warnings:
                        rec.warnings.append(note)
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    rec.timings["write"] = time.perf_counter() - t0
    report = rec.report()
    report["files"] = sorted([*paths, "report.json"] + (["report.html"] if html else []))
    if html:
        verts, faces, kind = _mesh_for_view(rec)
        paths["report.html"] = out / "report.html"
        atomic_write_text(paths["report.html"], _html(rec, report, paths["overlay.png"], paths["phase.png"],
                                                      verts, faces, kind))
    paths["report.json"] = out / "report.json"
    atomic_write_bytes(paths["report.json"], (json.dumps(report, indent=1) + "\n").encode())
    return paths
