"""The torch-free inference pipeline: one radar scan in, a dense point cloud out.

Stages (``Result.timings`` keys, seconds):

1. ``prepare``: pick the manifest's input columns (by name from a :class:`PointCloud`, by
   position from an array), float32.
2. ``voxelize``: crop to the grid and voxelize (numba; the crop is the voxelizer's half-open
   box test), then every encoder rulebook.
3. ``encoder``: ``encoder.onnx`` -> F^S (1, C, H, W).
4. ``adapter``: MSDNet: ``rgfd_adapter.onnx`` (F^S, eps) -> x_m. R2LDM: x_T = eps (pure noise).
   eps ~ N(0, I) comes from ``numpy.random.default_rng(seed)``, so a seed fixes the output.
5. ``denoise``: the DDIM loop, any step count chosen per call; each step runs the step graph
   with the coefficients of ``runtime.spec.ddim.step_coefficients`` (the update is inside the graph).
6. ``head``: ``recon_head.onnx`` -> occupancy (1, 8, D2, H2, W2), offsets (1, 8, 3, D2, H2, W2),
   full scale packed per half-scale voxel (``onnx_spec.RECON_HEAD``); or, when ``Pipeline.gate``
   is set (default: the manifest's calibrated ``gate``), the coarse-to-fine
   ``recon_head_sparse.onnx``: the full scale only under the half-scale voxels whose occupancy
   passes the gate (``onnx_spec.RECON_HEAD_SPARSE``), decoded by ``decode_sparse``.
7. ``decode``: threshold -> voxel centre + offset (numba), in linear voxel order; with range
   thresholds (manifest ``range_thresholds``, ``spec.range_threshold``) and no threshold given,
   each voxel at the threshold of its point's band of range; with
   ``keep_radar`` the input radar points inside the grid box are appended (confidence 1).
   With a keep threshold (manifest ``keep_radar_threshold``, ``Pipeline.keep_threshold``) each
   input radar point inside the grid box gets a confidence from the head's own output
   (``decode.radar_confidence_*``: the largest full-scale occupancy over the 3 x 3 x 3 voxels
   around it) and the points at or above the threshold are appended as they are; without one
   (older manifests) the output is what it always was, byte for byte.

Every input row the engine does not use is counted in ``Result.stats`` (``pointcloud.DROP_REASONS``): rows
with NaN/Inf (those a reader already dropped, ``PointCloud.dropped_nonfinite``, and those in the
array given), finite rows outside the grid box, and rows in the voxels over the ``max_voxels``
cap; ``dropped`` is their sum. Counting changes no output byte.

Buffers: F^S, the two ping-pong loop buffers and the head outputs are OrtValues allocated once
and bound once (IOBinding): the loop only writes the three step scalars and swaps bindings, no
array is copied per step. A Pipeline is therefore not thread-safe: use one per thread/process.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import onnxruntime as ort

from msdnet.runtime.engine.decode import (
    decode_packed,
    decode_sparse,
    packed_shape,
    radar_confidence_packed,
    radar_confidence_sparse,
)
from msdnet.runtime.engine.kernels import warmup as numba_warmup
from msdnet.runtime.engine.pairs import pair_feeds
from msdnet.runtime.engine.pointcloud import PointCloud
from msdnet.runtime.engine.rulebook import batch_coords, build_encoder_rulebooks
from msdnet.runtime.engine.voxelize import in_range_mask, voxelize
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.model import onnx_spec
from msdnet.runtime.model.artifact import Artifact, load_artifact
from msdnet.runtime.providers.session import AUTO, base_provider, create_session, device_of, precision_of
from msdnet.runtime.spec.cosine_logsnr import SamplerSettings, sampler_settings
from msdnet.runtime.spec.ddim import step_coefficients
from msdnet.runtime.spec.range_threshold import RangeThresholds

if TYPE_CHECKING:
    from msdnet.runtime.providers.provider_auto import AutoReport


@dataclass(frozen=True, eq=False)
class Result:
    """Output of one :class:`Pipeline` call."""

    points: np.ndarray  # (M, 3) float32 [x, y, z], radar frame, metres
    # (M,) float32 occupancy of each point's voxel, > threshold; a kept radar row's own confidence
    # (keep threshold); 1.0 on the other keep_radar rows
    confidence: np.ndarray
    timings: dict[str, float]  # seconds per stage (module docstring) and "total"
    # points_in, points_in_grid, voxels, steps, head_voxels (half-scale voxels decoded at full
    # scale; all of them with the dense head); with keep_radar or a keep threshold also radar_kept
    # (the radar rows at the end), with a keep threshold radar_confident (those kept by it);
    # the dropped rows by reason (pointcloud.DROP_REASONS keys) and their sum, dropped
    stats: dict[str, int] = field(default_factory=dict)
    notes: tuple[str, ...] = ()  # human-readable remarks, e.g. why the output is empty
    # (K,) float32 confidence of every input radar row inside the grid box (input order) when a
    # keep threshold is in force (``decode.radar_confidence_*``); None otherwise
    radar_confidence: np.ndarray | None = None


def _drop_counts(given: Any, pts: np.ndarray, in_grid: int, over_cap: int) -> dict[str, int]:
    """The rows of one scan the engine does not use, by reason (``pointcloud.DROP_REASONS``), summed:
    ``given`` the caller's input (a PointCloud carries the rows its reader dropped), ``pts`` the
    (N, C) rows voxelized, ``in_grid`` of them inside the grid box, ``over_cap`` of those in the
    voxels over the cap."""
    outside = int(pts.shape[0]) - in_grid  # non-finite rows included (the voxelizer's rule 1)
    here = int(pts.shape[0] - np.isfinite(pts).all(axis=1).sum()) if outside else 0
    counts = {
        "dropped_nonfinite": int(getattr(given, "dropped_nonfinite", 0)) + here,
        "dropped_outside_grid": outside - here,
        "dropped_over_cap": int(over_cap),
    }
    return counts | {"dropped": sum(counts.values())}


def _to_stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _empty_result(timings: dict[str, float], stats: dict[str, int], note: str) -> Result:
    return Result(np.empty((0, 3), np.float32), np.empty(0, np.float32), timings, stats, (note,))


class Pipeline:
    """An exported MSDNet (or R2LDM) folder, ready to run: ``Pipeline.from_dir(d)(points)``."""

    def __init__(
        self,
        artifact: Artifact,
        provider: str = "cpu",
        threads: int | None = None,
        notify: Callable[[str], None] | None = None,
    ):
        """``notify``: where ``provider`` ``auto[-bf16]`` says, in one line, that this load measured
        the engines (None: stderr)."""
        self.artifact = artifact  # checked manifest + graph bytes
        self.provider = provider  # short provider name (cpu, auto[-bf16], openvino[-bf16], cuda, tensorrt)
        self.kind = artifact.kind  # "student" or "r2ldm"
        self.columns = artifact.inputs.columns  # point columns the encoder expects, in order
        # keep radar points whose head occupancy around them reaches this (None: keep none)
        self.keep_threshold: float | None = artifact.keep_threshold
        # decoding thresholds by range band when no threshold is given (None: the manifest's one)
        self.range_thresholds: RangeThresholds | None = artifact.range_thresholds
        self.sessions: dict[str, ort.InferenceSession] = {}
        threads_of: dict[str, int | None] = {}  # graph file -> intra-op threads
        self.graph_threads = threads_of  # kept for logs and tests
        # onnxruntime's CPU DeformConv sums in an order that depends on the thread count (7e-7
        # apart on sim-lite), so with the byte-reproducible ``cpu`` provider the adapter always gets
        # one thread and the output bytes do not depend on ``threads`` (~2 ms a scan in lite, 150 ms
        # at paper width); the other providers promise no bytes and give it ``threads`` too.
        one = base_provider(provider) == "cpu"
        for spec in artifact.specs:
            n = threads_of[spec.file] = 1 if one and spec.file == onnx_spec.RGFD_ADAPTER.file else threads
            sess = create_session(artifact.graphs[spec.file], spec.file, provider, n)
            names_in = tuple(i.name for i in sess.get_inputs())
            names_out = tuple(o.name for o in sess.get_outputs())
            if names_in != spec.inputs or names_out != spec.outputs:
                raise MsdnetError(
                    spec.file,
                    f"graph inputs/outputs {names_in} -> {names_out} do not match the contract "
                    f"{spec.inputs} -> {spec.outputs}",
                )
            self.sessions[spec.file] = sess
        student = self.kind == "student"
        self._step_spec = onnx_spec.DENOISER_STEP if student else onnx_spec.R2LDM_STEP
        # R2LDM as published: the resampled cosine log-SNR loop (runtime/spec/cosine_logsnr.py); None:
        # the linear-schedule DDIM loop of runtime/spec/ddim.py
        block = artifact.manifest.get("sampler")
        self.sampler: SamplerSettings | None = None if block is None else sampler_settings(block)
        self._enc_spec = next(s for s in artifact.specs if s.file == onnx_spec.ENCODER.file)
        self._renoise: np.ndarray | None = None  # (K, 2) [a, b] of the last coefficients() call
        self.last_over_cap = 0  # rows in the voxels over the max_voxels cap, last encoder_feeds() call
        self._allocate(device_of(provider))
        self.auto: AutoReport | None = None  # provider "auto": each graph's engine, its times and why
        if base_provider(provider) == AUTO:
            from msdnet.runtime.providers.provider_auto import choose_engines

            self.auto = choose_engines(self, threads_of, precision_of(provider))  # may swap in OpenVINO's
            self._allocate(device_of(provider))  # so bind the buffers again
            if self.auto.dense_head:
                self.gate = None  # the dense reference is faster on these engines (provider_head)
            line = self.auto.summary()
            if line is not None:  # this load measured: say so once (the cache spares the next loads)
                (notify or _to_stderr)(line)

    @classmethod
    def from_dir(
        cls,
        path: str | Path,
        provider: str = "cpu",
        threads: int | None = None,
        notify: Callable[[str], None] | None = None,
    ) -> Pipeline:
        """Load and check an artifact folder (``msdnet-export`` output) and open its sessions."""
        return cls(load_artifact(path), provider=provider, threads=threads, notify=notify)

    # ------------------------------------------------------------------ buffers and bindings

    def _allocate(self, device: str) -> None:
        """Allocate every reused buffer once and bind what stays fixed between calls."""
        step = self.sessions[self._step_spec.file]
        shape = [int(d) if isinstance(d, int) else -1 for d in step.get_inputs()[0].shape]
        if len(shape) != 4 or min(shape) < 1 or shape[0] != 1:
            raise MsdnetError(self._step_spec.file, f"x_t must have a static (1, C, H, W) shape, got {shape}")
        stored = self.artifact.manifest.get("bev_shape")
        if stored is not None and list(stored) != shape:
            raise MsdnetError(self._step_spec.file, f"x_t shape {shape} != manifest bev_shape {stored}")
        self.bev_shape = tuple(shape)  # (1, C, H, W) of F^S and every loop buffer

        def buf(shape: tuple[int, ...]) -> ort.OrtValue:
            return ort.OrtValue.ortvalue_from_shape_and_type(list(shape), np.float32, device, 0)

        self._bev = buf(self.bev_shape)  # F^S: encoder output, adapter input / R2LDM condition
        self._x = (buf(self.bev_shape), buf(self.bev_shape))  # ping-pong loop buffers
        self._noise = np.empty(self.bev_shape, np.float32)  # eps, drawn in place per call
        self._scalars = {k: np.zeros(1, np.float32) for k in ("t", "abar_t", "abar_prev")}
        self._scalar_vals = {k: buf((1,)) for k in self._scalars}  # (1,) float32 step inputs
        half = packed_shape(self.artifact.grid)  # (D2, H2, W2)
        self._occ = np.empty((1, 8, *half), np.float32)  # head outputs (packed children), host memory
        self._off = np.empty((1, 8, 3, *half), np.float32)

        # Two step bindings: even steps read x[0] and write x[1], odd steps the reverse.
        self._step_bind = []
        for src, dst in ((0, 1), (1, 0)):
            b = step.io_binding()
            b.bind_ortvalue_input("x_t", self._x[src])
            for k, v in self._scalar_vals.items():
                b.bind_ortvalue_input(k, v)
            if self.kind == "r2ldm":
                b.bind_ortvalue_input("cond", self._bev)
            b.bind_ortvalue_output("x_prev", self._x[dst])
            self._step_bind.append(b)
        self._head_bind = []
        head = self.sessions[onnx_spec.RECON_HEAD.file]
        for out, arr in zip(head.get_outputs(), (self._occ, self._off), strict=True):
            if [d if isinstance(d, int) else -1 for d in out.shape] != list(arr.shape):
                raise MsdnetError(
                    onnx_spec.RECON_HEAD.file,
                    f"{out.name} shape {out.shape} != {list(arr.shape)} of the manifest grid",
                )
        for src in (0, 1):
            b = head.io_binding()
            b.bind_ortvalue_input("features", self._x[src])
            b.bind_ortvalue_output("occupancy", ort.OrtValue.ortvalue_from_numpy(self._occ))
            b.bind_ortvalue_output("offsets", ort.OrtValue.ortvalue_from_numpy(self._off))
            self._head_bind.append(b)
        self._allocate_sparse_head()
        self._enc_bind = self.sessions[onnx_spec.ENCODER.file].io_binding()
        self._enc_bind.bind_ortvalue_output("bev_features", self._bev)
        if self.kind == "student":
            self._adapter_bind = self.sessions[onnx_spec.RGFD_ADAPTER.file].io_binding()
            self._adapter_bind.bind_ortvalue_input("bev_features", self._bev)
            self._adapter_bind.bind_ortvalue_output("x_start", self._x[0])

    def _allocate_sparse_head(self) -> None:
        """Bindings of ``recon_head_sparse.onnx`` (when the artifact has it): features from either
        loop buffer; the gate and the outputs (dynamic N) are bound per call."""
        # half-scale occupancy gate; None: decode with the dense recon_head.onnx (the reference)
        self.gate: float | None = self.artifact.gate
        self._gate = np.zeros(1, np.float32)
        self._sparse_bind = []
        self._last_final: int | None = None  # loop buffer of the last sparse head call
        sess = self.sessions.get(onnx_spec.RECON_HEAD_SPARSE.file)
        if sess is None:
            return
        for src in (0, 1):
            b = sess.io_binding()
            b.bind_ortvalue_input("features", self._x[src])
            self._sparse_bind.append(b)

    def _head(
        self,
        final: int,
        thr: float,
        radar: np.ndarray | None = None,
        bands: RangeThresholds | None = None,
    ) -> tuple[np.ndarray, np.ndarray, int, np.ndarray | None]:
        """Head and decode stages on loop buffer ``final`` -> (points (M, 3), confidence (M,),
        half-scale voxels decoded at full scale, confidence (K,) of the ``radar`` rows (K, 3) or
        None without them). With ``bands`` each point is decoded at its range band's threshold."""
        grid = self.artifact.grid
        if self.gate is None:
            self._last_final = None  # sparse_head_outputs() is about the last call only
            self.sessions[onnx_spec.RECON_HEAD.file].run_with_iobinding(self._head_bind[final])
            self._timer("head")
            pts, conf = decode_packed(self._occ[0], self._off[0], grid, thr, bands)
            sure = None if radar is None else radar_confidence_packed(radar, self._occ[0], grid)
            return pts, conf, int(self._occ[0, 0].size), sure
        if not self._sparse_bind:
            raise MsdnetError(
                onnx_spec.RECON_HEAD_SPARSE.file, "gate set but the artifact has no sparse head"
            )
        if not 0.0 <= self.gate < 1.0:
            raise MsdnetError("gate", f"must be in [0, 1), got {self.gate}")
        self._gate[0] = self.gate
        self._last_final = final
        b = self._sparse_bind[final]
        b.bind_cpu_input("gate", self._gate)
        b.clear_binding_outputs()  # N changes per scan: onnxruntime allocates the outputs anew
        for name in onnx_spec.RECON_HEAD_SPARSE.outputs:
            b.bind_output(name, "cpu")
        self.sessions[onnx_spec.RECON_HEAD_SPARSE.file].run_with_iobinding(b)
        occ, off, vox, _ = b.get_outputs()
        self._timer("head")
        occ_np, vox_np = occ.numpy(), vox.numpy()
        pts, conf = decode_sparse(occ_np, off.numpy(), vox_np, grid, thr, bands)
        sure = None if radar is None else radar_confidence_sparse(radar, occ_np, vox_np, grid)
        return pts, conf, int(vox.shape()[0]), sure

    def sparse_head_outputs(self) -> dict[str, np.ndarray]:
        """The last call's ``recon_head_sparse.onnx`` outputs as numpy (``onnx_spec.RECON_HEAD_SPARSE``:
        occupancy (N, 8), offsets (N, 8, 3), voxels (N,), gate_occupancy (N,)); with gate 0, every
        half-scale voxel's (what ``export.gate`` calibrates on). Empty before a sparse call."""
        b = (
            self._sparse_bind[self._last_final]
            if self._sparse_bind and self._last_final is not None
            else None
        )
        if b is None:
            return {}
        return dict(
            zip(onnx_spec.RECON_HEAD_SPARSE.outputs, (v.numpy() for v in b.get_outputs()), strict=True)
        )

    # ------------------------------------------------------------------ stages

    def select_columns(self, points: np.ndarray | PointCloud) -> np.ndarray:
        """points: PointCloud (columns picked by name) or (N, C) array already in the manifest's
        column order -> (N, C) float32 contiguous. MsdnetError on a column mismatch."""
        if isinstance(points, PointCloud):
            return np.ascontiguousarray(points.select(self.columns).points, dtype=np.float32)
        arr = np.asarray(points)
        if arr.ndim != 2 or arr.shape[1] != len(self.columns):
            raise MsdnetError(
                None,
                f"points must be (N, {len(self.columns)}) [{' '.join(self.columns)}], got shape {arr.shape}",
            )
        return np.ascontiguousarray(arr, dtype=np.float32)

    def encoder_feeds(self, pts: np.ndarray) -> tuple[dict[str, np.ndarray], int, int]:
        """Voxelize ``pts`` (N, C) and build every encoder rulebook -> (``encoder.onnx`` inputs,
        points in grid, voxels); no inputs when there is no voxel. The rows over the voxel cap
        are kept in ``self.last_over_cap``."""
        vox = voxelize(pts, self.artifact.grid, self.artifact.inputs.max_voxels)
        n_vox, in_grid = int(vox.coords.shape[0]), pts.shape[0] - vox.dropped_out_of_range
        self.last_over_cap = int(vox.dropped_over_cap)
        if n_vox == 0:
            return {}, in_grid, 0
        coords = batch_coords([vox.coords])  # (V_0, 4) int32 [b = 0, z, y, x]
        rb = build_encoder_rulebooks(coords, self.artifact.grid.shape_zyx, onnx_spec.NUM_DOWN)
        if "voxel_counts" in self._enc_spec.inputs:  # the pair form (manifest encoder_form "pairs")
            levels = sum(
                name.startswith("down_") and name.endswith("_pairs_0") for name in self._enc_spec.inputs
            )
            pairs = {
                "voxel_features": np.ascontiguousarray(vox.features, np.float32),
                **pair_feeds(rb, levels),
            }
            return pairs, in_grid, n_vox
        feeds = {"voxel_features": vox.features, "subm_rules_0": rb.subm[0]}
        levels = sum(name.startswith("down_rules_") for name in self._enc_spec.inputs)
        for level in range(1, levels + 1):
            feeds[f"down_rules_{level}"] = rb.down[level - 1]
            feeds[f"subm_rules_{level}"] = rb.subm[level]
        feeds["bev_coords"] = rb.coords[levels]
        dtypes = {name: np.float32 if name == "voxel_features" else np.int64 for name in feeds}
        return {k: np.ascontiguousarray(v, dtype=dtypes[k]) for k, v in feeds.items()}, in_grid, n_vox

    def _encode(self, pts: np.ndarray) -> tuple[int, int]:
        """Voxelize ``pts`` (N, C) and run the encoder into F^S; -> (points in grid, voxels)."""
        feeds, in_grid, n_vox = self.encoder_feeds(pts)
        if n_vox == 0:
            return in_grid, 0
        self._timer("voxelize")
        for name, arr in feeds.items():
            self._enc_bind.bind_cpu_input(name, arr)
        self.sessions[onnx_spec.ENCODER.file].run_with_iobinding(self._enc_bind)
        return in_grid, n_vox

    def _timer(self, stage: str) -> None:
        now = time.perf_counter()
        self._timings[stage] = now - self._t
        self._t = now

    def coefficients(self, steps: int | None = None) -> np.ndarray:
        """(K, 3) float32 step-graph scalars, one row per network call, for ``steps`` (None: the
        manifest's): ``[t, abar_t, abar_prev]`` of the T_m DDIM steps; with a sampler block,
        ``[lambda_t, abar_t, abar_s]`` of every (repeated) call, and the re-noising after each
        call kept for the loop."""
        try:
            if self.sampler is not None:
                plan = self.sampler.plan(steps)
                self._renoise = plan.renoise
                return plan.coefficients
            return step_coefficients(self.artifact.diffusion, steps)
        except ValueError as err:
            raise MsdnetError("steps", str(err)) from None

    def __call__(
        self,
        points: np.ndarray | PointCloud,
        steps: int | None = None,
        threshold: float | None = None,
        seed: int = 0,
        *,
        keep_radar: bool = False,
        keep_threshold: float | None = None,
    ) -> Result:
        """Run one scan: points (N, C) float32 (manifest columns) or a PointCloud ->
        :class:`Result` with points (M, 3) float32 [x, y, z] and confidence (M,) float32.
        Same seed, same bytes: for any ``threads`` and in any process, given the same artifact,
        onnxruntime build and CPU (tested across threads 1/2 and msdnet-infer --workers 1/2).

        threshold: None (default): the manifest's ``range_thresholds`` when it has them (each point
        kept when its occupancy passes its range band's threshold), else its ``threshold``; a
        value: that one threshold everywhere.

        keep_radar: False (default): the model's decoded points only (M = M_model), confidence =
        occupancy. True: the model's points followed by the input radar points the model saw, i.e.
        the rows inside the grid box (``lo <= p < hi``, every column finite; the voxelizer's crop,
        count ``stats["points_in_grid"]``, before the max_voxels cap), in input order, x y z only,
        confidence 1.0: points (M_model + K, 3), confidence (M_model + K,), and the first M_model
        rows are exactly the output without the flag (same seed). ``stats["radar_kept"]`` = K.

        keep_threshold: None (default) takes ``Pipeline.keep_threshold`` (the manifest's
        ``keep_radar_threshold``; None in older manifests: the rules above, byte for byte). With a
        value in [0, 1]: the model's points are followed by the radar rows inside the grid box
        whose confidence (``Result.radar_confidence``, float32) is >= the value, in input order,
        x y z only, with that confidence (``stats["radar_confident"]`` rows); ``keep_radar``
        then appends the other radar rows (confidence 1.0) after them, so the output without the
        flag is again the first rows. ``stats["radar_kept"]``: the radar rows at the end.
        """
        bands = self.range_thresholds if threshold is None else None  # each point its band's
        thr = self.artifact.threshold if threshold is None else float(threshold)
        if not 0.0 < thr < 1.0:
            raise MsdnetError("threshold", f"must be in (0, 1), got {thr}")
        keep_thr = self.keep_threshold if keep_threshold is None else float(keep_threshold)
        if keep_thr is not None and not 0.0 <= keep_thr <= 1.0:
            raise MsdnetError("keep_threshold", f"must be in [0, 1], got {keep_thr}")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed: must be an integer >= 0 (the noise generator's seed), got {seed!r}")
        coeffs = self.coefficients(steps)
        n_steps = int(coeffs.shape[0]) if self.sampler is None else self.sampler.plan(steps).steps
        self._timings: dict[str, float] = {}
        self._t = start = time.perf_counter()
        pts = self.select_columns(points)
        self._timer("prepare")
        in_grid, n_vox = self._encode(pts)
        stats = {"points_in": int(pts.shape[0]), "points_in_grid": in_grid, "voxels": n_vox}
        stats |= _drop_counts(points, pts, in_grid, self.last_over_cap)
        stats["steps"] = n_steps  # DDIM steps; "network_calls" counts the repeats too
        stats["network_calls"] = int(coeffs.shape[0])
        if keep_radar or keep_thr is not None:
            stats["radar_kept"] = 0
        if keep_thr is not None:
            stats["radar_confident"] = 0
        if n_vox == 0:  # no row inside the grid box, so no radar point to keep either
            self._timer("voxelize")
            self._timings["total"] = time.perf_counter() - start
            why = "empty scan" if pts.shape[0] == 0 else "no point inside the grid"
            return _empty_result(self._timings, stats, f"{why}: no voxels, empty output")
        self._timer("encoder")
        rng = np.random.default_rng(seed)
        rng.standard_normal(dtype=np.float32, out=self._noise)
        if self.kind == "student":
            self._adapter_bind.bind_cpu_input("noise", self._noise)
            self.sessions[onnx_spec.RGFD_ADAPTER.file].run_with_iobinding(self._adapter_bind)
        else:
            self._x[0].update_inplace(self._noise)  # R2LDM starts from pure noise x_T
        self._timer("adapter")
        final = self._loop(coeffs, rng)
        self._timer("denoise")
        radar = None
        if keep_radar or keep_thr is not None:
            radar = np.ascontiguousarray(pts[in_range_mask(pts, self.artifact.grid), :3])
        out, conf, stats["head_voxels"], sure = self._head(
            final, thr, None if keep_thr is None else radar, bands
        )
        n_model = len(out)
        if radar is not None:
            extra, extra_conf = [radar], [np.ones(radar.shape[0], np.float32)]
            if sure is not None:
                kept = sure >= np.float32(keep_thr)
                stats["radar_confident"] = int(kept.sum())
                extra, extra_conf = [radar[kept]], [sure[kept]]
                if keep_radar:
                    extra.append(radar[~kept])
                    extra_conf.append(np.ones(int((~kept).sum()), np.float32))
            stats["radar_kept"] = sum(len(t) for t in extra)
            out = np.ascontiguousarray(np.concatenate([out, *extra]), dtype=np.float32)
            conf = np.concatenate([conf, *extra_conf])
        self._timer("decode")
        self._timings["total"] = time.perf_counter() - start
        notes: tuple[str, ...] = ()
        if n_model == 0:
            tail = "empty output" if len(out) == 0 else f"output is the {len(out)} radar points only"
            notes = (f"no voxel above the threshold: {tail}",)
        return Result(out, conf, self._timings, stats, notes, sure)

    def _loop(self, coeffs: np.ndarray, rng: np.random.Generator | None = None) -> int:
        """Run the DDIM steps in place on the ping-pong buffers; -> index of the final buffer.
        With a sampler, after call k with a finite re-noise row [a, b]: x <- a x + b eps, eps
        drawn from ``rng`` (the generator that drew x_T, so a seed fixes every draw)."""
        renoise = self._renoise if self.sampler is not None else None
        sess = self.sessions[self._step_spec.file]
        t, a_t, a_prev = (self._scalar_vals[k] for k in ("t", "abar_t", "abar_prev"))
        host = self._scalars
        for k in range(coeffs.shape[0]):
            host["t"][0], host["abar_t"][0], host["abar_prev"][0] = coeffs[k]
            t.update_inplace(host["t"])
            a_t.update_inplace(host["abar_t"])
            a_prev.update_inplace(host["abar_prev"])
            sess.run_with_iobinding(self._step_bind[k % 2])
            if renoise is not None and np.isfinite(renoise[k, 0]):
                if rng is None:
                    raise MsdnetError("sampler", "re-noising needs the call's random generator")
                out = self._x[(k + 1) % 2]
                eps = rng.standard_normal(self.bev_shape, dtype=np.float32)
                a, b = renoise[k]
                out.update_inplace(np.ascontiguousarray(a * out.numpy() + b * eps, dtype=np.float32))
        return coeffs.shape[0] % 2

    def warmup(self, runs: int = 1) -> None:
        """Compile the numba kernels and run the graphs ``runs`` times on a synthetic scan."""
        numba_warmup()
        lo = np.asarray(self.artifact.grid.point_range[:3], np.float32)
        hi = np.asarray(self.artifact.grid.point_range[3:], np.float32)
        rng = np.random.default_rng(0)
        pts = np.zeros((64, len(self.columns)), np.float32)
        pts[:, :3] = lo + (hi - lo) * rng.random((64, 3), dtype=np.float32)
        for _ in range(runs):
            self(pts, steps=1)

    def describe(self) -> dict[str, Any]:
        """Model kind, columns, grid, default steps and threshold: for logs and CLIs."""
        a = self.artifact
        return {
            "kind": a.kind,
            "columns": list(a.inputs.columns),
            "grid_zyx": list(a.grid.shape_zyx),
            "steps": a.diffusion.sample_steps,
            "threshold": a.threshold,
            "provider": self.provider,
        }
