"""The pure spec the model artifact and the engine share (numpy only; no session, no numba).

- ``grid``: the voxel grid (``GridConfig``, presets);
- ``ddim``, ``cosine_logsnr``: the diffusion schedules and the DDIM step coefficients;
- ``range_threshold``: decoding thresholds by band of horizontal range.

The artifact checks a manifest against them and the engine runs them; both import them from
here, so neither imports the other to get them.
"""
