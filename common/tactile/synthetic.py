"""Synthetic tactile frames: an LDPE pipette pressed between two flat pads.

The model is there so the classifier, the simulated sensors and the tests
share one idea of what a real grasp looks like, including what makes real
frames hard: a light grip that barely crosses the sensor's 1 N floor, a
squeezed tube whose band is wide and uneven, two pads that do not agree, and
taxels that are dead, stuck, noisy or mis-calibrated. It is NumPy only and
in ``common`` because the operator's perception study simulates grasps too.

Conventions (the project's tactile contract, declared in ``common.tactile.contract``):

- A frame is float32 newtons of shape ``FRAME_SHAPE``: axis 0 the pad (0 = finger
  1, 1 = finger 2 already mirrored into finger 1's view), axis 1 the row (0 at
  the fingertip end, "up"), axis 2 the column (0 at the left).
- The pads are 10 x 10 taxels at a 2.41 mm pitch (about 24.1 mm square).
  Below 1 N a taxel reads 0; above 9 N it saturates at 9 N.
- Angle class 0..3 is theta = 0, 45, 90, 135 deg, the pipette's axis measured
  counter-clockwise from the row direction with up towards row 0, so 45 deg
  runs from lower left to upper right.
- Position class 0 is centre; 1 is left (towards column 0) for 45, 90 and 135
  deg and up (towards row 0) for 0 deg; 2 is the other side. The offset is
  perpendicular to the axis, about 6 mm.
- ``pattern = 3 * angle_class + position_class``.

Physics, in the order ``frame`` applies it: the grip level sets how far the
gripper has closed on the tube (the Robotiq levels are positions), which
sets both the line load (N per mm of pipette) and how wide the tube has
flattened; the tube's cross-section gives the pressure profile across the
band (Hertz-like when barely touched, edge-loaded when a hollow tube is
squashed); the pad's elastomer cover blurs it; each taxel integrates the
pressure over its area; then the sensor adds its gain spread, calibration
residual, noise, floor, saturation and defects.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from common.tactile.contract import (
    ANGLES_DEG,
    FRAME_SHAPE,
    N_GRIP_LEVELS,
    N_PATTERNS,
    PAD_COLS,
    PAD_ROWS,
    classes_of,
)
from common.tactile.synthetic_params import GeneratorParams

#: subsamples per taxel side used to integrate pressure over a taxel's area
_SUB = 4


def offset_direction(angle_class: int) -> tuple[float, float]:
    """Unit vector (x right, y up, in mm space) of position class 1's offset.

    Position 1 means "towards column 0" for the tilted and vertical bands and
    "towards row 0" for the horizontal one; the offset is always perpendicular
    to the band's axis, so it is the axis normal with that sign.
    """
    theta = math.radians(ANGLES_DEG[angle_class])
    nx, ny = -math.sin(theta), math.cos(theta)
    towards_class_1 = ny > 0 if angle_class == 0 else nx < 0  # up is +y, left is -x
    sign = 1.0 if towards_class_1 else -1.0
    return sign * nx, sign * ny


def mirror_finger2(frame: np.ndarray) -> np.ndarray:
    """Swap pad 2 between its own (wire) view and the common view.

    Finger 2 faces finger 1, so its columns run the other way; reversing them
    is its own inverse. Simulated boards call this to put pad 2 on the wire as
    the real sensor would, and drivers call it to bring it back.
    """
    out = np.array(frame, copy=True)
    out[..., 1, :, :] = out[..., 1, :, ::-1]
    return out


@dataclass(frozen=True)
class Grasp:
    """One grasp's geometry and unevenness; the grip level is applied on top."""

    pattern: int
    theta_deg: float  # actual axis angle, counter-clockwise from the rows, up = row 0
    centre_mm: tuple[float, float]  # a point on the axis, from the pad centre (x right, y up)
    width_scale: float  # this grasp's band width against the level's nominal width
    load_scale: float  # this grasp's line load against the level's nominal load
    taper: float  # relative width change per 12 mm along the axis
    gradient: float  # relative load change per 12 mm along the axis
    ripple: float  # amplitude of the load's variation along the axis
    wavelength_mm: float
    phase: float
    bend: float  # -1..1, scaled by bend_max_mm and the squeeze
    pad_share: tuple[float, float]  # load share of finger 1 and finger 2
    tip: tuple[float, float] | None  # (direction, mm along the axis) where the pipette ends


class SyntheticTactileModel:
    """One simulated sensor pair: its defects are fixed by ``seed``, its grasps vary.

    The per-sensor state (which taxels are dead or stuck, each taxel's gain
    and zero residual, how finger 2 sits against finger 1) is drawn once, as a
    real pair of pads carries its flaws from frame to frame. Everything about
    a single grasp comes from the ``rng`` passed to ``frame``, so a caller
    owns reproducibility of the sequence.
    """

    def __init__(self, params: GeneratorParams | None = None, seed: int = 0) -> None:
        self.params = params = GeneratorParams() if params is None else params
        rng = np.random.default_rng(seed)
        shape = FRAME_SHAPE
        self.gain = np.exp(rng.normal(0.0, params.gain_spread, shape))
        pad2_gain = max(0.2, 1.0 + rng.normal(0.0, params.pad_gain_mismatch))
        self.gain[1] *= pad2_gain
        self.zero_offset = rng.normal(0.0, params.zero_offset_n, shape)
        u = rng.random(shape)
        self.dead_mask = u < params.dead_taxel_fraction
        self.stuck_mask = (u >= params.dead_taxel_fraction) & (
            u < params.dead_taxel_fraction + params.stuck_taxel_fraction
        )
        self.stuck_values_n = np.where(
            self.stuck_mask, rng.uniform(params.stuck_min_n, params.stuck_max_n, shape), 0.0
        )
        shift = rng.normal(0.0, params.pad_misregistration_mm, 2)
        rot = math.radians(rng.normal(0.0, params.pad_rotation_deg))

        # Sample points inside every taxel, in mm from the pad centre, x right
        # and y up. Pad 2's points are where its taxels really sit in finger
        # 1's frame after its mounting error.
        pitch = params.pitch_mm
        k = (np.arange(PAD_COLS * _SUB) + 0.5) / _SUB - PAD_COLS / 2
        xs = k * pitch
        ys = -((np.arange(PAD_ROWS * _SUB) + 0.5) / _SUB - PAD_ROWS / 2) * pitch
        x1, y1 = np.meshgrid(xs, ys)
        c, s = math.cos(rot), math.sin(rot)
        x2 = c * x1 - s * y1 + shift[0]
        y2 = s * x1 + c * y1 + shift[1]
        self._x = np.stack([x1, x2])  # (2, 10*SUB, 10*SUB)
        self._y = np.stack([y1, y2])
        self._sample_area = (pitch / _SUB) ** 2
        self._half_extent = pitch * max(PAD_ROWS, PAD_COLS) / 2

    @property
    def defects(self) -> dict[str, np.ndarray]:
        """This sensor's fixed flaws, in the common view: for tests and live views."""
        return {
            "dead": self.dead_mask.copy(),
            "stuck": self.stuck_mask.copy(),
            "stuck_values_n": self.stuck_values_n.astype(np.float32),
            "gain": self.gain.astype(np.float32),
        }

    def draw_grasp(self, pattern: int, rng: np.random.Generator) -> Grasp:
        """Where and how one grasp holds the pipette, fixed while it is held.

        A simulated sensor streaming one grasp draws this once and renders
        every frame of the grasp from it, so the band does not jump between
        frames; ``frame`` draws a fresh grasp each call.
        """
        _check(pattern, 1)
        p = self.params
        angle_class, position_class = classes_of(pattern)
        theta_deg = ANGLES_DEG[angle_class] + rng.uniform(-1, 1) * p.angle_jitter_deg
        theta = math.radians(theta_deg)
        nx, ny = -math.sin(theta), math.cos(theta)  # across the actual axis
        ox, oy = offset_direction(angle_class)
        nominal = (0.0, p.side_offset_mm, -p.side_offset_mm)[position_class]
        # The nominal offset follows the class's direction; the error is across
        # the actual (jittered) axis, where it changes what the taxels see.
        err = rng.uniform(-1, 1) * p.offset_jitter_mm
        jitter = np.exp(rng.normal(0.0, p.grip_jitter, 2))
        balance = rng.normal(0.0, p.pad_balance_jitter)
        tip = None
        if p.tip_on_pad_probability > 0 and rng.random() < p.tip_on_pad_probability:
            tip = (float(rng.choice((-1.0, 1.0))), rng.uniform(-0.3, 0.6) * self._half_extent)
        return Grasp(
            pattern=pattern,
            theta_deg=theta_deg,
            centre_mm=(nominal * ox + err * nx, nominal * oy + err * ny),
            width_scale=float(jitter[0]),
            load_scale=float(jitter[1]),
            taper=rng.uniform(-1, 1) * p.taper_per_12mm,
            gradient=rng.uniform(-1, 1) * p.along_band_gradient,
            ripple=rng.uniform(0, 1) * p.along_band_ripple,
            wavelength_mm=rng.uniform(10.0, 30.0),
            phase=rng.uniform(0, 2 * math.pi),
            bend=rng.uniform(-1, 1),
            pad_share=(max(0.3, 1.0 + balance), max(0.3, 1.0 - balance)),
            tip=tip,
        )

    def contact_force(self, grasp: Grasp | None, grip_level: int) -> np.ndarray:
        """Force on each taxel (N, float64) before the sensor's electronics touch it."""
        _check(None if grasp is None else grasp.pattern, grip_level)
        if grasp is None:
            return np.zeros(FRAME_SHAPE)
        p = self.params
        squeeze = (grip_level - 1) / (N_GRIP_LEVELS - 1)
        theta = math.radians(grasp.theta_deg)
        ux, uy = math.cos(theta), math.sin(theta)  # along the pipette
        nx, ny = -uy, ux  # across it
        width = p.pipette_diameter_mm * (
            p.width_min_fraction + (p.width_max_fraction - p.width_min_fraction) * squeeze
        )
        half_width = 0.5 * width * grasp.width_scale
        load = (
            p.line_load_min_n_per_mm
            + (p.line_load_max_n_per_mm - p.line_load_min_n_per_mm) * squeeze**p.load_exponent
        ) * grasp.load_scale
        edge = p.edge_loading_max * squeeze
        bend = grasp.bend * p.bend_max_mm * squeeze

        dx = self._x - grasp.centre_mm[0]
        dy = self._y - grasp.centre_mm[1]
        t = dx * ux + dy * uy  # along the axis, mm
        d = dx * nx + dy * ny  # across it, mm
        d = d - bend * ((t / self._half_extent) ** 2 - 1.0 / 3.0)
        local_half = half_width * np.clip(1.0 + grasp.taper * t / 12.0, 0.5, 1.5)
        # Line load per mm along the band, then spread across the band by the
        # cross-section's profile (unit integral), then blurred by the cover.
        q = load * np.clip(1.0 + grasp.gradient * t / 12.0, 0.2, None)
        q = q * (1.0 + grasp.ripple * np.sin(2 * math.pi * t / grasp.wavelength_mm + grasp.phase))
        if grasp.tip is not None:
            sign, t_end = grasp.tip
            q = np.where(sign * t <= t_end, q, 0.0)
        pressure = q * _blurred_profile(d, half_width, local_half, edge, p.cover_blur_mm)
        pressure *= np.asarray(grasp.pad_share)[:, None, None]
        force = pressure.reshape(2, PAD_ROWS, _SUB, PAD_COLS, _SUB).sum(axis=(2, 4))
        return force * self._sample_area

    def frame(self, pattern: int | None, grip_level: int, rng: np.random.Generator) -> np.ndarray:
        """A ``FRAME_SHAPE`` float32 frame in newtons, as the pad pair would report it.

        ``pattern`` None means nothing is grasped: only taxels stuck above the
        floor read anything. ``grip_level`` runs 1 (lightest) to 31. Each call
        is a new grasp (a new small error in angle and offset).
        """
        _check(pattern, grip_level)
        grasp = None if pattern is None else self.draw_grasp(pattern, rng)
        return self.grasp_frame(grasp, grip_level, rng)

    def grasp_frame(
        self, grasp: Grasp | None, grip_level: int, rng: np.random.Generator
    ) -> np.ndarray:
        """A frame of a grasp drawn by ``draw_grasp`` (None: nothing grasped)."""
        return self.sense(self.contact_force(grasp, grip_level), rng)

    def sense(self, force: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """What the electronics make of a true force map: gains, noise, floor, defects."""
        p = self.params
        reading = self.gain * force + self.zero_offset
        sigma = p.noise_n + p.noise_relative * np.abs(reading)
        reading = reading + sigma * rng.standard_normal(FRAME_SHAPE)
        reading = np.minimum(reading, p.saturation_n)
        reading[reading < p.floor_n] = 0.0
        reading[self.dead_mask] = 0.0
        reading[self.stuck_mask] = self.stuck_values_n[self.stuck_mask]
        return reading.astype(np.float32)


def _check(pattern: int | None, grip_level: int) -> None:
    if pattern is not None and not 0 <= pattern < N_PATTERNS:
        raise ValueError(f"pattern must be 0..{N_PATTERNS - 1} or None, not {pattern!r}")
    if not 1 <= grip_level <= N_GRIP_LEVELS:
        raise ValueError(f"grip_level must be 1..{N_GRIP_LEVELS}, not {grip_level!r}")


#: step of the 1-D grid on which the cover's blur is convolved, mm
_GRID_MM = 0.02


def _blurred_profile(
    d: np.ndarray, half_width: float, local_half: np.ndarray, edge: float, blur_mm: float
) -> np.ndarray:
    """Pressure per unit line load (1/mm) at distance ``d`` across the band.

    The undisturbed profile is sqrt(1 - u^2) * (1 - e + 2 e u^2) for
    u = d / half_width: e = 0 is Hertz contact of a cylinder on a flat; a
    larger e moves the load to the edges, where a squashed hollow tube's walls
    fold. The cover's Gaussian spread is convolved on a fine 1-D grid (a thin
    band is narrower than a taxel, so sampling it coarsely would flicker).
    A taper stretches the blurred profile locally, keeping its unit integral.
    """
    reach = 1.6 * half_width + 4.0 * blur_mm + _GRID_MM
    z = np.arange(-reach, reach + _GRID_MM / 2, _GRID_MM)
    raw = _profile(z / half_width, edge)
    if blur_mm > 0:
        k = np.arange(-4.0 * blur_mm, 4.0 * blur_mm + _GRID_MM / 2, _GRID_MM)
        kernel = np.exp(-0.5 * (k / blur_mm) ** 2)
        if kernel.size < raw.size:
            raw = np.convolve(raw, kernel / kernel.sum(), mode="same")
    raw /= raw.sum() * _GRID_MM
    scale = half_width / local_half
    return np.interp(d * scale, z, raw, left=0.0, right=0.0) * scale


def _profile(u: np.ndarray, edge: float) -> np.ndarray:
    inside = np.clip(1.0 - u * u, 0.0, None)
    return np.sqrt(inside) * (1.0 - edge + 2.0 * edge * np.minimum(u * u, 1.0))


class HeldGrasp:
    """Frames of scripted grasps with the pipette still while each is held.

    A new grasp (a new small error in angle and offset) is drawn when the
    pattern changes or after a release; between, only the grip level and the
    taxel noise change, as when a real gripper holds a pipette.
    """

    def __init__(self, model: SyntheticTactileModel, rng: np.random.Generator) -> None:
        self.model = model
        self.rng = rng
        self._grasp: Grasp | None = None
        self._pattern: int | None = None
        #: the held grasp's force map by grip level: the same grasp at the same level presses
        #: the same (only the sensor's noise is new each frame), and the map was nine tenths
        #: of a frame's cost, at 120 frames a second in every scripted node
        self._force: dict[int, np.ndarray] = {}

    def frame(self, pattern: int | None, grip_level: int | None) -> np.ndarray:
        if pattern is None:
            self._grasp = self._pattern = None
            self._force.clear()
            return self.model.grasp_frame(None, 1, self.rng)
        if self._grasp is None or pattern != self._pattern:
            self._grasp = self.model.draw_grasp(pattern, self.rng)
            self._pattern = pattern
            self._force.clear()
        level = grip_level or 1
        force = self._force.get(level)
        if force is None:
            force = self._force[level] = self.model.contact_force(self._grasp, level)
        return self.model.sense(force, self.rng)
