"""ONNX graph contracts: file names, input/output names and dynamic axes, declared once.

Both the exporter (``msdnet.export``) and the runtime (``msdnet.runtime.engine.pipeline``) import this
module; it must stay torch-free. Shapes use ``V_l`` for the voxel count at encoder level ``l``
(level 0 = input voxels, each down layer halves the grid) and ``C`` for ``bev_channels``.
"""

from __future__ import annotations

from dataclasses import dataclass

FORMAT_VERSION = 1  # bump when the artifact layout or any contract below changes
OPSET = 19  # ONNX opset of every graph (DeformConv needs >= 19)
NUM_DOWN = 3  # stride-2 layers in the sparse encoder: the BEV map is at 1/8 of the grid
KERNEL_TAPS = 27  # 3 x 3 x 3 sparse kernel


@dataclass(frozen=True)
class GraphSpec:
    """One ONNX graph of an artifact folder."""

    file: str  # file name inside the artifact folder
    inputs: tuple[str, ...]  # input names, in the order the torch module's forward takes them
    outputs: tuple[str, ...]  # output names, in order
    dynamic_axes: dict[str, dict[int, str]]  # per input/output: axis -> symbolic name


def _encoder_spec(levels: int = NUM_DOWN) -> GraphSpec:
    inputs = ["voxel_features", "subm_rules_0"]  # (V_0, F) float32 ; (V_0, 27) int64
    axes: dict[str, dict[int, str]] = {"voxel_features": {0: "V_0"}, "subm_rules_0": {0: "V_0"}}
    for level in range(1, levels + 1):
        for kind in ("down", "subm"):
            name = f"{kind}_rules_{level}"  # (V_level, 27) int64, rows index level-1 / level
            inputs.append(name)
            axes[name] = {0: f"V_{level}"}
    inputs.append("bev_coords")  # (V_3, 4) int64 [b, z, y, x] of the last level, for the scatter
    axes["bev_coords"] = {0: f"V_{levels}"}
    return GraphSpec("encoder.onnx", tuple(inputs), ("bev_features",), axes)


ENCODER = _encoder_spec()  # voxels + rulebooks -> F^S (1, C, H, W)
RGFD_ADAPTER = GraphSpec(  # F_r^S, eps (1, C, H, W) -> x_m (1, C, H, W), Eq. 12
    "rgfd_adapter.onnx", ("bev_features", "noise"), ("x_start",), {}
)
DENOISER_STEP = GraphSpec(  # one DDIM step: x_t (1, C, H, W), t/abar_t/abar_prev (1,) -> x_prev
    "denoiser_step.onnx", ("x_t", "t", "abar_t", "abar_prev"), ("x_prev",), {}
)
# F^D (1, C, H, W) -> full-scale occupancy (1, 8, D2, H2, W2) and offsets (1, 8, 3, D2, H2, W2)
# [dx, dy, dz], packed: axis 1 is the child (dz * 2 + dy) * 2 + dx of half-scale voxel [z2, y2, x2]
# (full-scale voxel [2 z2 + dz, 2 y2 + dy, 2 x2 + dx]); runtime.engine.decode.decode_packed reads it.
RECON_HEAD = GraphSpec("recon_head.onnx", ("features",), ("occupancy", "offsets"), {})
MSDNET_GRAPHS = (ENCODER, RGFD_ADAPTER, DENOISER_STEP, RECON_HEAD)
# Coarse-to-fine head (optional; used with the manifest's ``gate``): F^D (1, C, H, W), gate (1,)
# -> the full scale only under the N half-scale voxels whose own occupancy > gate: occupancy
# (N, 8), offsets (N, 8, 3) [dx, dy, dz] (children as in RECON_HEAD), voxels (N,) int64 linear
# half-scale index (z2 * H2 + y2) * W2 + x2, increasing; gate_occupancy (N,) the voxels' own
# occupancy. runtime.engine.decode.decode_sparse reads it.
RECON_HEAD_SPARSE = GraphSpec(
    "recon_head_sparse.onnx",
    ("features", "gate"),
    ("occupancy", "offsets", "voxels", "gate_occupancy"),
    {"occupancy": {0: "N"}, "offsets": {0: "N"}, "voxels": {0: "N"}, "gate_occupancy": {0: "N"}},
)
OPTIONAL_GRAPHS = (RECON_HEAD_SPARSE,)  # either kind may carry these; older artifacts lack them

# R2LDM baseline: same encoder and head contracts; its step takes the radar latent as condition.
R2LDM_STEP = GraphSpec(  # x_t, cond (1, C, H, W), t/abar_t/abar_prev (1,) -> x_prev
    "r2ldm_step.onnx", ("x_t", "cond", "t", "abar_t", "abar_prev"), ("x_prev",), {}
)
R2LDM_GRAPHS = (ENCODER, R2LDM_STEP, RECON_HEAD)

# R2LDM as published (manifest ``sampler.name`` = runtime.spec.cosine_logsnr.SAMPLER_NAME): the encoder
# stops at level 2 (latent at 1/4 of the grid, bev_coords (V_2, 4)); the step's ``t`` is the
# log-SNR; the runtime's loop re-noises between repeated steps; recon_head.onnx is the LPCR decoder.
ENCODER_QUARTER = _encoder_spec(2)
R2LDM_PUBLISHED_GRAPHS = (ENCODER_QUARTER, R2LDM_STEP, RECON_HEAD)


ENCODER_FORMS = ("rulebook", "pairs")  # manifest "encoder_form"; absent: rulebook
PAIR_GROUPS = {"subm": 1, "down": 1}  # tap groups per layer kind (runtime.engine.pairs)


def encoder_pairs_spec(levels: int = NUM_DOWN) -> GraphSpec:
    """``encoder.onnx`` in the pair form (runtime.engine.pairs): voxel_features (V_0, F) float32,
    voxel_counts (levels + 1,) int64 V_l, per conv layer and tap group ``<layer>_pairs_<g>``
    (2, taps, P) int64 [input rows; output rows], bev_pairs (2, D8, P) int64 -> F^S (1, C, H, W)."""
    inputs = ["voxel_features", "voxel_counts"]
    axes: dict[str, dict[int, str]] = {"voxel_features": {0: "V_0"}}
    layers = ["subm_0"] + [f"{kind}_{level}" for level in range(1, levels + 1) for kind in ("down", "subm")]
    for layer in layers:
        for g in range(PAIR_GROUPS[layer.split("_")[0]]):
            name = f"{layer}_pairs_{g}"
            inputs.append(name)
            axes[name] = {2: f"P_{layer}_{g}"}
    inputs.append("bev_pairs")
    axes["bev_pairs"] = {2: "P_bev"}
    return GraphSpec("encoder.onnx", tuple(inputs), ("bev_features",), axes)


def encoder_spec_of(spec: GraphSpec, form: str) -> GraphSpec:
    """The encoder contract ``spec`` (rulebook form, any levels) in ``form``."""
    if form == "rulebook":
        return spec
    return encoder_pairs_spec(sum(name.startswith("down_rules_") for name in spec.inputs))


def graphs_of(kind: str, sampler: object, by_kind: dict[str, tuple[GraphSpec, ...]]) -> tuple[GraphSpec, ...]:
    """The required graphs of a ``kind`` artifact: ``by_kind[kind]``, or the published R2LDM's
    when the manifest names a sampler (only R2LDM has one)."""
    return R2LDM_PUBLISHED_GRAPHS if kind == "r2ldm" and sampler else by_kind[kind]
