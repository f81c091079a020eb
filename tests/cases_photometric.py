"""Jacobian cases of the photometric factors (``factors/photometric.py``), and a tiny
numpy renderer of textured planes used by ``tests/test_direct.py`` and the benchmark.

Image choice for the numeric checks: bilinear interpolation is only piecewise smooth
and DSO's interpolated central-difference gradient is not the derivative of the
interpolated intensity. So most cases sample an ``AnalyticImage`` (a smooth
sum-of-sinusoids-and-Gaussians function of the pixel coordinates with its exact
gradient): the residual is then C-infinity in the state and the numeric derivative
is meaningful everywhere. One case per factor uses a ``BilinearImage`` with
``gradient="exact"`` (the interpolant's own derivative) at a state whose target
pixels are all >= 0.05 px from pixel-cell boundaries.

The factors' weights are frozen IRLS weights (Huber and the V-dependent seed weight);
the cases disable Huber and use V = 0 so the weight is a constant and the factor's
residual function is exactly differentiable.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from factors.image_ops import AnalyticImage, BilinearImage, SmoothTexture
from factors.photometric_shutter import Shutter
from factors.photometric import (Pinhole, PhotometricParams, make_host_patch, stereo_eval,
                                 stereo_factor, stereo_residual_fn, temporal_eval,
                                 temporal_factor, temporal_residual_fn)
from factors.photometric_point import StereoTerm, point_factor, point_kinds, point_residual_fn
from factors.photometric_warp import row_model
from jacobian_case import JacobianCase

W, H = 640, 480
K = Pinhole(450.0, 452.0, 318.0, 243.0)
CHECK_PARAMS = PhotometricParams(sigma_I=4.0, grad_c=50.0, huber_k=None)
X = gtsam.symbol_shorthand.X
D = gtsam.symbol_shorthand.D
A = gtsam.symbol_shorthand.A


def random_pose(rng: np.random.Generator, rot: float = np.pi, trans: float = 2.0) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * rot / 2),
                       rng.normal(size=3) * trans)


def analytic_image(rng: np.random.Generator) -> AnalyticImage:
    # features of 13-250 px: smooth enough that the O(delta^2) error of the central
    # differences stays far below the suite's 1e-6 tolerance
    return AnalyticImage(SmoothTexture.random(rng, extent=W, wavelength=(0.1, 0.4),
                                              width=(0.02, 0.06)), W, H)


def _point_seen_at(T_w_ci: gtsam.Pose3, T_w_cj: gtsam.Pose3, uv_j: np.ndarray, z_j: float):
    """Host pixel and inverse depth of the point seen at target pixel ``uv_j`` at depth z_j."""
    p_cj = np.append((uv_j - [K.cx, K.cy]) / [K.fx, K.fy], 1.0) * z_j
    p_ci = T_w_ci.transformTo(T_w_cj.transformFrom(p_cj))
    return K.project(p_ci), 1.0 / p_ci[2]


LENS = {"radial-tangential": (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05),    # EuRoC cam0
        "equidistant": (0.0034823894, 0.0007150348, -0.0020532361, 0.0002029367)}        # TUM-VI cam0
"""Lens coefficients of the rolling-shutter cases whose row times are sensor rows."""


def _shutter(rng: np.random.Generator, rolling: bool | str) -> Shutter | None:
    """A rolling shutter of 0.1 ms a row (48 ms readout, 3x the rendered test sequence's)
    with random host and target twists of ~1 rad/s and ~1 m/s, or None; ``rolling`` a
    ``LENS`` name: the row times are the sensor rows through that lens."""
    if not rolling:
        return None
    rows = row_model((K.fx, K.fy, K.cx, K.cy), rolling, LENS[rolling]) if isinstance(rolling, str) else None
    return Shutter(1e-4, rng.normal(0, 1.0, 6), rng.normal(0, 1.0, 6), rows, rows)


def _frac_ok(uv: np.ndarray, margin: float = 0.05) -> bool:
    f = uv - np.floor(uv)
    return bool(np.all((f > margin) & (f < 1 - margin)))


def temporal_case(name: str, *, rho_target: float | None = None, baseline: float = 0.15,
                  uv_j: tuple[float, float] | None = None, zero_affine: bool = False,
                  identity_extrinsic: bool = False, bilinear: bool = False,
                  degenerate: bool = False, rolling: bool | str = False) -> JacobianCase:
    """A temporal factor at a random state; options select the degenerate variants;
    ``rolling``: both images with a rolling shutter (``factors.photometric_shutter.Shutter``; a
    ``LENS`` name: its rows bent by that lens)."""

    def build(rng: np.random.Generator):
        target = analytic_image(rng)
        host_img = analytic_image(rng)
        if bilinear:
            target = BilinearImage(target.render(), gradient="exact")
        T_b_c = gtsam.Pose3() if identity_extrinsic else random_pose(rng, 1.0, 0.05)
        for _ in range(200):
            T_w_bi = random_pose(rng)
            step = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 0.05),
                               rng.normal(size=3) * baseline / np.sqrt(3))
            T_w_bj = T_w_bi.compose(step)
            z_j = 1.0 / rho_target if rho_target else rng.uniform(0.7, 6.0)
            uvj = np.array(uv_j, float) if uv_j else rng.uniform([40, 40], [W - 40, H - 40])
            uv_i, rho = _point_seen_at(T_w_bi.compose(T_b_c), T_w_bj.compose(T_b_c), uvj, z_j)
            if not (rho > 0 and 5 < uv_i[0] < W - 6 and 5 < uv_i[1] < H - 6):
                continue
            host = make_host_patch(host_img, uv_i[None], K)
            ab_i = np.zeros(2) if zero_affine else rng.normal([0, 0], [0.3, 10.0])
            ab_j = np.zeros(2) if zero_affine else rng.normal([0, 0], [0.3, 10.0])
            shutter = _shutter(rng, rolling)
            fn = temporal_residual_fn(host, target, K, T_b_c, CHECK_PARAMS, shutter=shutter)
            if bilinear:
                ev = temporal_eval(T_w_bi, T_w_bj, np.array([rho]), ab_i, ab_j, host, target,
                                   K, T_b_c)
                if not _frac_ok(ev.uv[ev.valid]):
                    continue
            break
        else:
            raise RuntimeError(f"{name}: no valid random state found")
        keys = [X(0), X(1), D(0), A(0), A(1)]
        factor = temporal_factor(keys, host, target, K, T_b_c, CHECK_PARAMS, shutter=shutter)
        values = gtsam.Values()
        values.insert(keys[0], T_w_bi)
        values.insert(keys[1], T_w_bj)
        values.insert(keys[2], np.array([rho]))
        values.insert(keys[3], ab_i)
        values.insert(keys[4], ab_j)

        def residual(vals: gtsam.Values):
            return fn([vals.atPose3(keys[0]), vals.atPose3(keys[1]), vals.atVector(keys[2]),
                       vals.atVector(keys[3]), vals.atVector(keys[4])])

        return factor, values, residual, ["pose3", "pose3", 1, 2, 2]

    return JacobianCase(name, build, degenerate)


def stereo_case(name: str, *, baseline: float = 0.11, rho_range=(0.1, 1.5), bilinear: bool = False,
                degenerate: bool = False, rolling: bool | str = False) -> JacobianCase:
    """A static stereo factor (left host -> right target) at a random state (``rolling``:
    both cameras with a rolling shutter, a ``LENS`` name: through that lens)."""

    def build(rng: np.random.Generator):
        target = analytic_image(rng)
        if bilinear:
            target = BilinearImage(target.render(), gradient="exact")
        left = analytic_image(rng)
        T_r_l = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 0.01),
                            np.array([-baseline, 0.0, 0.0]) + rng.normal(size=3) * baseline * 0.02)
        for _ in range(200):
            uv = rng.uniform([60, 30], [W - 30, H - 30])
            rho = rng.uniform(*rho_range)
            host = make_host_patch(left, uv[None], K)
            ab = rng.normal([0, 0], [0.2, 8.0])
            shutter = _shutter(rng, rolling)
            ev = stereo_eval(np.array([rho]), ab, host, target, K, T_r_l, shutter=shutter)
            if ev.valid.all() and (not bilinear or _frac_ok(ev.uv)):
                break
        else:
            raise RuntimeError(f"{name}: no valid random state found")
        params = PhotometricParams(sigma_I=4.0, huber_k=None, weight=0.5)
        fn = stereo_residual_fn(host, target, K, T_r_l, params, shutter=shutter)
        factor = stereo_factor([D(0), A(0)], host, target, K, T_r_l, params, shutter=shutter)
        values = gtsam.Values()
        values.insert(D(0), np.array([rho]))
        values.insert(A(0), ab)

        def residual(vals: gtsam.Values):
            return fn([vals.atVector(D(0)), vals.atVector(A(0))])

        return factor, values, residual, [1, 2]

    return JacobianCase(name, build, degenerate)


def point_case(name: str, *, n_targets: int = 3, stereo: bool = True, bilinear: bool = False,
               degenerate: bool = False) -> JacobianCase:
    """A multi-target point factor (``point_factor``): one host point seen in
    ``n_targets`` target keyframes, optionally with the static stereo term at the host."""

    def build(rng: np.random.Generator):
        host_img = analytic_image(rng)
        T_b_c = random_pose(rng, 1.0, 0.05)
        T_r_l = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 0.01),
                            np.array([-0.11, 0.0, 0.0]) + rng.normal(size=3) * 0.002)
        for _ in range(200):
            T_w_bi = random_pose(rng)
            uv = rng.uniform([80, 60], [W - 80, H - 60])
            rho = rng.uniform(0.2, 1.2)
            host = make_host_patch(host_img, uv[None], K)
            poses = [T_w_bi.compose(gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 0.03),
                                                rng.normal(size=3) * 0.05))
                     for _ in range(n_targets)]
            imgs = [analytic_image(rng) for _ in range(n_targets)]
            right = analytic_image(rng)
            ok = True
            for T_j, im in zip(poses, imgs):
                ev = temporal_eval(T_w_bi, T_j, np.array([rho]), np.zeros(2), np.zeros(2), host,
                                   im, K, T_b_c)
                ok &= bool(ev.valid.all()) and (not bilinear or _frac_ok(ev.uv))
            if ok:
                break
        else:
            raise RuntimeError(f"{name}: no valid random state found")
        if bilinear:   # rendered only now: the target pixels do not depend on the image
            imgs = [BilinearImage(im.render(), gradient="exact") for im in imgs]
        term = StereoTerm(right, K, T_r_l, PhotometricParams(huber_k=None, weight=0.7)) if stereo else None
        fn = point_residual_fn(host, imgs, K, T_b_c, CHECK_PARAMS, term)
        keys = [X(0), D(0), A(0)] + ([A(99)] if stereo else [])
        for m in range(n_targets):
            keys += [X(m + 1), A(m + 1)]
        kinds = point_kinds(n_targets, stereo)
        values = gtsam.Values()
        values.insert(X(0), T_w_bi)
        values.insert(D(0), np.array([rho]))
        values.insert(A(0), rng.normal([0, 0], [0.3, 10.0]))
        if stereo:
            values.insert(A(99), rng.normal([0, 0], [0.2, 8.0]))
        for m, T_j in enumerate(poses):
            values.insert(X(m + 1), T_j)
            values.insert(A(m + 1), rng.normal([0, 0], [0.3, 10.0]))
        factor = point_factor(keys, host, imgs, K, T_b_c, CHECK_PARAMS, term)

        def residual(vals: gtsam.Values):
            args = [vals.atPose3(k) if kd == "pose3" else vals.atVector(k) for k, kd in zip(keys, kinds)]
            r, J = fn(args)
            dims = [6 if kd == "pose3" else kd for kd in kinds]
            ends = np.cumsum([0] + dims)
            return r, [J[:, a:b] for a, b in zip(ends[:-1], ends[1:])]

        return factor, values, residual, kinds

    return JacobianCase(name, build, degenerate)


CASES: list[JacobianCase] = [
    point_case("photometric_point_stereo_3_targets"),
    point_case("photometric_point_temporal_only", n_targets=2, stereo=False),
    point_case("photometric_point_bilinear_exact", n_targets=1, bilinear=True),
    point_case("photometric_point_stereo_only", n_targets=0, degenerate=True),
    temporal_case("photometric_temporal_random"),
    temporal_case("photometric_temporal_identity_extrinsic", identity_extrinsic=True),
    temporal_case("photometric_temporal_bilinear_exact", bilinear=True),
    temporal_case("photometric_temporal_zero_affine", zero_affine=True, degenerate=True),
    temporal_case("photometric_temporal_near_border", uv_j=(W - 3.3, 200.4), degenerate=True),
    temporal_case("photometric_temporal_tiny_baseline", baseline=1e-4, degenerate=True),
    temporal_case("photometric_temporal_far_point", rho_target=1e-3, degenerate=True),
    temporal_case("photometric_temporal_rolling_shutter", rolling=True),
    temporal_case("photometric_temporal_rolling_shutter_far_point", rho_target=1e-3, rolling=True,
                  degenerate=True),
    temporal_case("photometric_temporal_rolling_shutter_radtan_lens", rolling="radial-tangential"),
    temporal_case("photometric_temporal_rolling_shutter_fisheye_lens", rolling="equidistant"),
    stereo_case("photometric_stereo_random"),
    stereo_case("photometric_stereo_bilinear_exact", bilinear=True),
    stereo_case("photometric_stereo_tiny_baseline", baseline=1e-3, degenerate=True),
    stereo_case("photometric_stereo_far_point", rho_range=(1e-4, 1e-3), degenerate=True),
    stereo_case("photometric_stereo_rolling_shutter", rolling=True),
    stereo_case("photometric_stereo_rolling_shutter_radtan_lens", rolling="radial-tangential"),
]


# ----------------------------------------------------------------------------- renderer

@dataclass(frozen=True)
class TexturedPlane:
    """A plane through ``origin`` spanned by unit ``e1``, ``e2`` (world frame, metres);
    intensity ``texture(x1, x2)`` in plane coordinates."""

    origin: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    texture: SmoothTexture


def cast_planes(planes: list[TexturedPlane], K_cam: Pinhole, T_w_c: gtsam.Pose3, u: np.ndarray,
                v: np.ndarray, gain: float = 1.0, bias: float = 0.0
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ray-cast the nearest plane through pixels (u, v) (any shape, sub-pixel allowed).

    Returns intensity gain * texture + bias, inverse depth (camera z, 1/m) and the hit
    mask; intensity and inverse depth are 0 where nothing is hit.
    """
    d_c = K_cam.unproject(np.stack(np.broadcast_arrays(u, v), -1))
    d_w = d_c @ T_w_c.rotation().matrix().T
    o = T_w_c.translation()
    best = np.full(d_c.shape[:-1], np.inf)
    which = np.full(d_c.shape[:-1], -1)
    for i, pl in enumerate(planes):
        n = np.cross(pl.e1, pl.e2)
        den = d_w @ n
        lam = np.where(np.abs(den) > 1e-12, ((pl.origin - o) @ n) / np.where(den == 0, 1, den), -1)
        hit = (lam > 1e-3) & (lam < best)
        best = np.where(hit, lam, best)
        which = np.where(hit, i, which)
    img = np.zeros(d_c.shape[:-1])
    for i, pl in enumerate(planes):  # texture only where this plane is the nearest
        m = which == i
        X = o + best[m][:, None] * d_w[m] - pl.origin
        img[m] = pl.texture(X @ pl.e1, X @ pl.e2)[0]
    hit = which >= 0
    idepth = np.where(hit, 1.0 / np.where(hit, best, 1.0), 0.0)
    return gain * img + bias * hit, idepth, hit


def render_planes(planes: list[TexturedPlane], K_cam: Pinhole, T_w_c: gtsam.Pose3, width: int,
                  height: int, gain: float = 1.0, bias: float = 0.0
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Point-sampled image (H, W) at every pixel centre and its inverse depth map (H, W)."""
    vv, uu = np.mgrid[0:height, 0:width].astype(np.float64)
    img, idepth, _ = cast_planes(planes, K_cam, T_w_c, uu, vv, gain, bias)
    return img, idepth


@dataclass(frozen=True, eq=False)
class PlaneSampler:
    """An ``ImageSampler`` that ray-casts the scene at the exact sub-pixel position (no
    interpolation); gradient by central differences of 1e-3 px. Same margins as
    BilinearImage."""

    planes: list
    K: Pinhole
    T_w_c: gtsam.Pose3
    width: int
    height: int
    gain: float = 1.0
    bias: float = 0.0

    def sample(self, u, v):
        u, v = np.broadcast_arrays(np.asarray(u, float), np.asarray(v, float))
        I, _, hit = cast_planes(self.planes, self.K, self.T_w_c, u, v, self.gain, self.bias)
        h = 1e-3
        gx = (cast_planes(self.planes, self.K, self.T_w_c, u + h, v, self.gain, self.bias)[0]
              - cast_planes(self.planes, self.K, self.T_w_c, u - h, v, self.gain, self.bias)[0]) / (2 * h)
        gy = (cast_planes(self.planes, self.K, self.T_w_c, u, v + h, self.gain, self.bias)[0]
              - cast_planes(self.planes, self.K, self.T_w_c, u, v - h, self.gain, self.bias)[0]) / (2 * h)
        valid = hit & (u >= 1) & (u < self.width - 2) & (v >= 1) & (v < self.height - 2)
        return I, gx, gy, valid


@dataclass(frozen=True, eq=False)
class NoiseTexture:
    """Non-periodic texture: white noise blurred at two scales on a texel grid, bilinear.

    ``__call__(x, y)`` (metres; wraps with period size * texel) -> (I, dI/dx, dI/dy) like
    SmoothTexture.
    """

    image: BilinearImage
    texel: float

    @staticmethod
    def random(rng: np.random.Generator, size: int = 1024, texel: float = 0.004,
               scales_m: tuple[float, ...] = (0.008, 0.03), contrast: float = 40.0) -> "NoiseTexture":
        fy = np.fft.fftfreq(size)[:, None]
        fx = np.fft.rfftfreq(size)[None, :]
        img = np.zeros((size, size))
        for sc in scales_m:
            sig = sc / texel
            spec = np.fft.rfft2(rng.normal(size=(size, size)))
            blur = np.fft.irfft2(spec * np.exp(-2 * (np.pi * sig) ** 2 * (fx ** 2 + fy ** 2)), s=(size, size))
            img += blur / blur.std()
        img = 128.0 + contrast * img / img.std()
        return NoiseTexture(BilinearImage(np.clip(img, 5, 250), gradient="exact"), texel)

    def __call__(self, x, y):
        n = self.image.width - 4.0  # wrap inside the valid sampling range [1, n + 1)
        u = np.mod(np.asarray(x) / self.texel, n) + 1.0
        v = np.mod(np.asarray(y) / self.texel, n) + 1.0
        I, gx, gy, _ = self.image.sample(u, v)
        return I, gx / self.texel, gy / self.texel


def box_scene(rng: np.random.Generator, depth: float = 2.5,
              scales_m: tuple[float, ...] = (0.008, 0.03)) -> list[TexturedPlane]:
    """A back wall at z = depth, a floor and a left wall (world = first camera frame,
    z forward, y down), each with a random non-periodic texture of blobs of ``scales_m``."""
    def tex():
        return NoiseTexture.random(rng, scales_m=scales_m)
    ex, ey, ez = np.eye(3)
    return [TexturedPlane(np.array([-1.5, -1.5, depth]), ex, ey, tex()),
            TexturedPlane(np.array([-1.5, 0.9, -0.5]), ex, ez, tex()),
            TexturedPlane(np.array([-1.4, -1.5, -0.5]), ey, ez, tex())]
