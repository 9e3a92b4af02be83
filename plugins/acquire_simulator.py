"""Acquisition from the built-in station simulator (the default source).

Renders ``frames`` noisy stereo pairs of a named scenario
(:mod:`crossfield.simulator.scenarios`); the geometry is fixed by the
scenario, the noise by ``seed``, so a session is reproducible. The source
also drives the simulated ROMER arm on a pseudo-terminal: see
:meth:`SimulatorSource.serve_arm`.
"""

from __future__ import annotations

import contextlib
import time
from typing import Any, Iterator

import numpy as np

from crossfield.plugin_api import (
    SCENARIOS,
    Acquisition,
    Register,
    SimulatedArm,
    StereoFrame,
    build_scene,
    hookimpl,
    read_stereo_calibration,
)


class SimulatorSource:
    """Stereo pairs rendered by the station simulator.

    scenario: ``station`` (the paper's set-up), ``table3`` (the paper's
    ten cross-field lengths) or ``camera-limited`` (precise reference, small
    tilted targets). frames: number of stereo pairs. seed: noise seed
    (images and arm). arm_sigma_mm: CMM arm noise per coordinate (mm);
    unset = the scenario's own (0.01, or 0.001 for ``camera-limited``).
    start_time_ns: capture time of the first pair (ns since the Unix epoch;
    0 = now); pairs follow at the camera's 14 Hz. calibration: a FileStorage
    calibration file (e.g. written by ``crossfield calibrate --scenario``) that
    the session measures with instead of the rig's true calibration; the
    images are still rendered through the true one ("" = the truth).
    """

    def __init__(
        self,
        *,
        scenario: str = "station",
        frames: int = 10,
        seed: int = 1,
        arm_sigma_mm: float | None = None,
        start_time_ns: int = 0,
        calibration: str = "",
    ) -> None:
        if scenario not in SCENARIOS:
            raise ValueError(f"option 'scenario': unknown scenario {scenario!r}; scenarios: {', '.join(SCENARIOS)}")
        if not isinstance(frames, int) or frames < 1:
            raise ValueError(f"option 'frames' must be a positive integer, got {frames!r}")
        if arm_sigma_mm is not None and not arm_sigma_mm >= 0:
            raise ValueError(f"option 'arm_sigma_mm' must be >= 0, got {arm_sigma_mm!r}")
        self.scenario = scenario
        self.n_frames = frames
        self.seed = seed
        self.scene = build_scene(scenario, arm_sigma_mm=arm_sigma_mm)
        self.calibration = self.scene.calibration
        self.calibration_file = calibration
        if calibration:

            self.calibration = read_stereo_calibration(
                calibration, image_sizes=(self.calibration.upper.image_size, self.calibration.lower.image_size)
            )
        self.ground_truth = self.scene.ground_truth
        self.default_plan = self.scene.plan
        self.start_time_ns = start_time_ns  # 0: taken when the first pair is acquired

    def frames(self) -> Iterator[StereoFrame]:
        rng = np.random.default_rng([self.seed, 1])
        if not self.start_time_ns:
            self.start_time_ns = time.time_ns()
        period_ns = round(1e9 / self.scene.frame_rate_hz)
        for sequence in range(self.n_frames):
            yield self.scene.render_pair(sequence, rng, self.start_time_ns + sequence * period_ns)

    def arm_probes(self):
        """The arm's points for this session (deterministic from ``seed``)."""
        return self.scene.arm_probes(np.random.default_rng([self.seed, 2]))

    @contextlib.contextmanager
    def serve_arm(self) -> Iterator[str]:
        """Run the simulated ROMER arm on a pseudo-terminal; yields its tty path."""

        with SimulatedArm(self.arm_probes()).serve_pty() as port:
            yield port

    def describe(self) -> dict[str, Any]:
        s = self.scene
        return {
            "source": "simulator",
            "scenario": self.scenario,
            "frames": self.n_frames,
            "seed": self.seed,
            "camera_model": "Basler scA1600-14gm (simulated)",
            "image_size": list(s.calibration.upper.image_size),
            "bit_depth": s.sensor.bit_depth,
            "sensor": {
                "gain_dn_per_e": s.sensor.gain_dn_per_e,
                "read_noise_dn": s.sensor.read_noise_dn,
                "blur_sigma_px": s.sensor.blur_sigma_px,
            },
            "arm_sigma_mm": s.arm_sigma_mm,
            "targets": len(s.targets),
            "calibration_file": self.calibration_file or None,
        }

    def close(self) -> None:
        pass


@hookimpl
def register_acquires(register: Register[Acquisition]) -> None:
    register("simulator", SimulatorSource, "Built-in station simulator (paper's set-up), deterministic")
