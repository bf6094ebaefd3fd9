"""Warehouse flight simulator: trajectory, rendering, IMU synthesis, scenarios, `simulate()`.

from fusion.sim import simulate
result = simulate(Path("flights/sim0"), "default", duration_s=60.0, seed=0)
"""

from fusion.sim.imu import synthesize_imu, synthesize_velocity
from fusion.sim.render import (
    PlacedCode,
    RenderEffects,
    code_texture,
    project_code_corners,
    render_view,
)
from fusion.sim.scenarios import SCENARIOS, Scenario, build_scenario
from fusion.sim.simulate import SimulationResult, simulate
from fusion.sim.trajectory import (
    Keyframe,
    KeyframeTrajectory,
    TrueState,
    survey_keyframes,
)

__all__ = [
    "PlacedCode",
    "RenderEffects",
    "code_texture",
    "project_code_corners",
    "render_view",
    "synthesize_imu",
    "synthesize_velocity",
    "SCENARIOS",
    "Scenario",
    "build_scenario",
    "SimulationResult",
    "simulate",
    "Keyframe",
    "KeyframeTrajectory",
    "TrueState",
    "survey_keyframes",
]
