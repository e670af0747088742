"""The simulated lab's settings: where things stand, how soft they are, how fast it steps.

One ``LabWorldConfig`` describes one world. The three lab device kinds (tactile
pads, gripper, arm) name the same world through ``world_config`` (a TOML file
of these fields, or the shipped default), so they attach to one process.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from common.config.typed import param
from common.errors import ConfigError


@dataclass
class PipetteConfig:
    x_m: float = param(0.0, "offset from the rack centre along the rack row (m, base frame)")
    tilt_deg: float = param(0.0, "lean in the grasp plane from vertical (deg, + = top towards +x)")
    radius_mm: float = param(4.5, "outer radius of the pipette's stem where it is grasped")


def _three_pipettes() -> list[PipetteConfig]:
    return [
        PipetteConfig(x_m=-0.06, tilt_deg=0.0),
        PipetteConfig(x_m=0.0, tilt_deg=0.0),
        PipetteConfig(x_m=0.06, tilt_deg=30.0),
    ]


@dataclass
class LabWorldConfig:
    seed: int = param(0, "seeds the pads' defects, calibration and noise")
    timestep_s: float = param(0.002, "physics step; 2 ms keeps the soft pad contact stable")
    rack_centre_m: tuple[float, float] = param(
        (0.0, 0.0), "rack centre (x, y) relative to the tool's home position (m, base frame)"
    )
    pipette_top_below_tcp_m: float = param(
        0.005, "pipette tops this far below the fingertip centre at home: jog down to grasp"
    )
    pipettes: list[PipetteConfig] = param(_three_pipettes(), "the pipettes in the rack")
    taxel_solref: tuple[float, float] = param(
        (0.01, 1.0), "contact time constant and damping of a taxel: the pad's softness"
    )
    taxel_solimp: tuple[float, float, float] = param(
        (0.05, 0.95, 0.003), "contact impedance (dmin, dmax, width m): soft at first touch"
    )
    pipette_travel_m: float = param(
        0.1, "how far a pipette slides up out of its rack hole along its axis before it is free"
    )
    pipette_mass_kg: float = param(
        3.0,
        "a pipette's mass as the engine sees it: a 10 ml pipette weighs ~10 g, but MuJoCo's soft "
        "contact against so light a body on a slide is soft too, and the lowest grip levels "
        "would press no taxel past 1 N; 3 kg keeps the pads as stiff as against a fixed "
        "pipette (what gravity pulls is pipette_weight_kg)",
    )
    pipette_weight_kg: float = param(
        0.3,
        "what gravity pulls on a pipette, the rest of its engine mass floating (MuJoCo's "
        "gravcomp): a real one weighs ~10 g, but against the 3 kg it moves with it would "
        "fall back into its hole 300 times too slowly; at 0.3 kg a lift needs 3 N of "
        "friction, not 30, and a released pipette drops 40 mm in 0.3 s",
    )
    pipette_damping_n_s_m: float = param(2.0, "the rack hole's sliding damping")
    friction_impratio: float = param(
        10.0,
        "how much stiffer friction is than the normal contact (MuJoCo's impratio): at 1 a "
        "held pipette creeps down soft pads under its engine weight, and a 40 mm lift drew "
        "it only 19 to 35 mm up",
    )
    pipette_friction: float = param(
        1.0,
        "sliding friction between the pads and a pipette (silicone on plastic): both the "
        "taxels and the pipettes get it, as MuJoCo takes the larger of a contact's two",
    )
    gripper_mass_kg: float = param(
        5.0,
        "the welded gripper's mass: the wrist and arm behind it, so a squeeze does not "
        "soften against a light body",
    )
    wrist_weld_solref: tuple[float, float] = param(
        (0.004, 1.0), "how stiffly the gripper follows the flange (time constant s, damping ratio)"
    )
    finger_kp_n_m: float = param(40000.0, "finger position servo stiffness (N/m)")
    finger_force_min_n: float = param(20.0, "grip force at FOR 0 (2F-85: 20 N)")
    finger_force_max_n: float = param(235.0, "grip force at FOR 255 (2F-85: 235 N)")
    finger_stroke_mm: float = param(42.5, "travel of each finger from open to closed (2F-85)")
    open_gap_mm: float = param(
        73.0, "distance between the two pads' surfaces when open: level 1 touches"
    )
    table_clearance_m: float = param(
        0.002, "an arm link or the gripper this close to the table top is a collision"
    )

    def __post_init__(self) -> None:
        if not 0 < self.pipette_weight_kg <= self.pipette_mass_kg:
            raise ConfigError("lab world: pipette_weight_kg must be in (0, pipette_mass_kg]")
        if not math.isfinite(self.friction_impratio) or self.friction_impratio < 1:
            raise ConfigError("lab world: friction_impratio must be at least 1")
        if not 0 < self.timestep_s <= 0.01:
            raise ConfigError("lab world: timestep_s must be in (0, 0.01] s")
        if not self.pipettes:
            raise ConfigError("lab world: the rack needs at least one pipette")
        if not 0 < self.finger_force_min_n <= self.finger_force_max_n:
            raise ConfigError("lab world: need 0 < finger_force_min_n <= finger_force_max_n")
