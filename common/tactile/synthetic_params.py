"""What a synthetic grasp depends on: the pad, the pipette's place and press, the flaws.

Each parameter carries its physical reason; ``common.tactile.synthetic``
draws grasps and frames from them.
"""

from __future__ import annotations

from dataclasses import dataclass

from common.config.typed import param
from common.tactile.contract import CONTACT_FLOOR_N, SATURATION_N


@dataclass
class GeneratorParams:
    """Everything the synthetic grasp depends on, each with its physical reason."""

    # --- the pad -----------------------------------------------------------
    pitch_mm: float = param(2.41, "taxel pitch: 10 taxels over a 5.8 cm^2 pad (24.1 mm)")
    floor_n: float = param(CONTACT_FLOOR_N, "the sensor's floor: a taxel below 1 N reads 0")
    saturation_n: float = param(SATURATION_N, "the sensor's ceiling: a taxel above 9 N reads 9 N")
    cover_blur_mm: float = param(
        0.6, "std dev of the elastomer cover's spreading of a point load onto the taxels"
    )
    # --- where the pipette lies --------------------------------------------
    side_offset_mm: float = param(
        6.0, "perpendicular distance of a left/right (up/down) band from the pad centre"
    )
    angle_jitter_deg: float = param(
        4.0, "largest error of the pipette's angle: the grasp is never exactly square"
    )
    offset_jitter_mm: float = param(
        1.0, "largest error of the band's perpendicular offset from its nominal place"
    )
    # --- the pipette and the grip ------------------------------------------
    pipette_diameter_mm: float = param(
        6.0, "outer diameter of the LDPE Pasteur pipette's stem where it is grasped"
    )
    width_min_fraction: float = param(
        0.15, "contact band width / diameter at grip level 1: a barely flattened tube"
    )
    width_max_fraction: float = param(
        1.0, "contact band width / diameter at level 31: the tube squashed flat"
    )
    line_load_min_n_per_mm: float = param(
        1.1, "load per mm of pipette at level 1: the lightest grip that registers"
    )
    line_load_max_n_per_mm: float = param(
        8.0, "load per mm at level 31: the band's centre taxels reach saturation"
    )
    load_exponent: float = param(
        1.3, "load ~ squeeze^k: a collapsing tube stiffens as its walls meet"
    )
    grip_jitter: float = param(
        0.1, "relative spread of load and width at one level (creep, grasp point on the taper)"
    )
    edge_loading_max: float = param(
        0.6, "at full squeeze a hollow tube presses hardest at its folded edges (0 = Hertz)"
    )
    taper_per_12mm: float = param(
        0.08, "max relative change of band width per 12 mm along the axis: the stem tapers"
    )
    along_band_gradient: float = param(
        0.2, "max relative change of load per 12 mm along the band: pads not quite parallel"
    )
    along_band_ripple: float = param(
        0.15, "amplitude of load variation along the band: a moulded tube is not uniform"
    )
    bend_max_mm: float = param(
        0.6, "max sag of the band's centre line at full squeeze: the soft tube bows"
    )
    tip_on_pad_probability: float = param(
        0.0, "chance the pipette's end lies on the pad, so the band stops short"
    )
    # --- two pads that do not agree ----------------------------------------
    pad_gain_mismatch: float = param(
        0.1, "std dev of finger 2's overall gain relative to finger 1 (per sensor)"
    )
    pad_misregistration_mm: float = param(
        0.4, "std dev of finger 2's shift against finger 1 (per sensor): mounting tolerance"
    )
    pad_rotation_deg: float = param(
        1.0, "std dev of finger 2's rotation against finger 1 (per sensor)"
    )
    pad_balance_jitter: float = param(
        0.08, "std dev of the load share between the pads per grasp: the fingers flex unequally"
    )
    # --- taxels -------------------------------------------------------------
    gain_spread: float = param(
        0.08, "std dev of per-taxel gain (log-normal): calibration is never perfect"
    )
    zero_offset_n: float = param(
        0.05, "std dev of per-taxel zero residual left after taring with nothing grasped"
    )
    noise_n: float = param(0.08, "std dev of taxel read noise in newtons, per frame")
    noise_relative: float = param(
        0.03, "extra noise proportional to the reading: piezoresistive drift under load"
    )
    dead_taxel_fraction: float = param(
        0.01, "fraction of taxels that always read 0 (broken traces, per sensor)"
    )
    stuck_taxel_fraction: float = param(
        0.002, "fraction of taxels stuck at a fixed reading (shorted traces, per sensor)"
    )
    stuck_min_n: float = param(1.5, "lowest reading a stuck taxel is stuck at")
    stuck_max_n: float = param(SATURATION_N, "highest reading a stuck taxel is stuck at")

    def __post_init__(self) -> None:
        positive = ("pitch_mm", "pipette_diameter_mm", "saturation_n", "width_max_fraction")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, not {getattr(self, name)!r}")
        non_negative = (
            "floor_n", "cover_blur_mm", "side_offset_mm", "angle_jitter_deg",
            "offset_jitter_mm", "width_min_fraction", "line_load_min_n_per_mm",
            "line_load_max_n_per_mm", "load_exponent", "grip_jitter", "edge_loading_max",
            "taper_per_12mm", "along_band_gradient", "along_band_ripple", "bend_max_mm",
            "pad_gain_mismatch", "pad_misregistration_mm", "pad_rotation_deg",
            "pad_balance_jitter", "gain_spread", "zero_offset_n", "noise_n", "noise_relative",
        )  # fmt: skip
        for name in non_negative:
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must not be negative, not {getattr(self, name)!r}")
        for name in ("tip_on_pad_probability", "dead_taxel_fraction", "stuck_taxel_fraction"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"{name} must be in 0..1, not {getattr(self, name)!r}")
        if self.dead_taxel_fraction + self.stuck_taxel_fraction > 1:
            raise ValueError("dead_taxel_fraction + stuck_taxel_fraction must not exceed 1")
        if self.floor_n >= self.saturation_n:
            raise ValueError("floor_n must be below saturation_n")
        if self.stuck_min_n > self.stuck_max_n:
            raise ValueError("stuck_min_n must not exceed stuck_max_n")
        if self.edge_loading_max > 1:
            raise ValueError("edge_loading_max must be in 0..1")
