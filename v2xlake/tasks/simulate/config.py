"""Configuration of the multi-agent recorder simulator (``SimConfig``) and its two presets.

Presets (``SimConfig.preset(name, **overrides)``):

* ``cats`` follows CATS-V2V main paper Tab. 2: 128-beam LiDAR, 0.2 deg azimuth (1800 columns
  per 0.1 s scan), vertical FOV -25..15 deg, dual return (strongest + last); seven cameras at
  30 Hz: CAM_FRONT (wide), CAM_FRONT_NARROW (tele), CAM_BACK at 3840x2160, four side cameras at
  1920x1536 on ``black`` and 1920x1080 on ``red``.
* ``small`` is the same rig at test scale: 32 beams, 1 deg azimuth (360 columns), single return,
  120 m range, all seven cameras scaled to 640 px wide (aspect kept: 640x360 front/back,
  640x360 / 640x512 sides). Tests should pass ``cameras=("CAM_FRONT", "CAM_BACK")`` and/or a
  lower ``camera_hz`` (stamps stay on the 30 Hz trigger grid, every n-th trigger is rendered).
* ``street`` is the hard street of issue #13 on the ``small`` rig (pass ``lidar=`` for full
  size): ``street="corridor"`` (a long straight street between continuous parallel facades,
  sparse poles, dense moving traffic in both directions, one 90 deg turn at an intersection
  with corner buildings, the other agent 5..25 m ahead in the next lane), only ``black``'s
  published LiDAR extrinsic wrong (15 cm / 0.4 deg), the reference agent's exact, and an INS
  drift of 3 cm/s per agent (a few cm/s between the agents), 10 m/s city speed.
* ``coop`` is the cooperative-registration scenario of issue #21 (``street="boulevard"``, see
  ``scene``): a straight boulevard between walls at +-14 m from its centre line, 20 poles,
  6 parked cars, an oncoming car, a truck and a pedestrian crossing; ``red`` at 15 m/s turns
  at 0.25 rad/s for 1 s (and back 2 s later when the clip holds the whole turn back),
  ``black`` drives straight at 16 m/s in the adjacent lane 20 m behind (``coop_gap_m``);
  64-beam 1024-column 10 Hz single-return LiDAR 1.9 m above the ground, no cameras; exact,
  noise-free INS written as ``nav_msgs/Odometry``; only ``black``'s published LiDAR extrinsic
  wrong, by exactly (0.12, -0.08, 0.05) m and +0.4 deg yaw (``lidar_ext_err_xyz_m`` /
  ``lidar_ext_err_rpy_deg``). Variations are overrides of the same fields (the module doc of
  ``scene`` and ``tests/fixtures/street.py`` list them).

Every number that tests relate to (extrinsic errors, INS bias, noise) is a field here, so a
test can switch an error source off and check the geometry exactly. The whole config is
written to ``truth/sim_config.json`` so that ``v2xlake.tasks.simulate.truth.load_truth`` can rebuild
the analytic trajectories and scene of a clip bit-for-bit.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

CAMERA_NAMES: tuple[str, ...] = (
    "CAM_FRONT", "CAM_FRONT_NARROW", "CAM_BACK", "CAM_FRONT_LEFT", "CAM_BACK_LEFT",
    "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT",
)
AGENT_NAMES: tuple[str, ...] = ("red", "black", "rsu")


class LidarSpec(BaseModel):
    """Mechanical spinning LiDAR, phase-locked to the PPS at 0 deg azimuth.

    ``columns`` azimuth columns per revolution at ``rate_hz``; all ``beams`` lasers of a column
    fire at the same instant (one timestamp per column).
    """

    model_config = ConfigDict(frozen=True)

    beams: int = Field(128, ge=2)
    columns: int = Field(1800, ge=36)
    rate_hz: float = 10.0
    elev_min_deg: float = -25.0
    elev_max_deg: float = 15.0
    max_range_m: float = 250.0
    min_range_m: float = 0.5
    dual_return: bool = True
    range_noise_m: float = Field(0.0, ge=0.0, description="Gaussian range noise sigma")


class SimConfig(BaseModel):
    """Everything that determines a simulated clip; same config + seed -> same bytes."""

    model_config = ConfigDict(frozen=True)

    preset_name: str = "small"
    seconds: float = Field(2.0, gt=0.0, le=120.0)
    storage: Literal["sqlite3", "mcap", "ros1"] = "sqlite3"
    seed: int = 0
    agents: tuple[str, ...] = ("red", "black")
    clip_id: str | None = Field(None, description="default: sim_<preset_name>_s<seed>")
    start_s: int = Field(1_700_000_000, description="GNSS epoch second of the first PPS")
    origin_lat: float = 42.2936
    origin_lon: float = -83.7130
    ground_alt_m: float = 250.0
    lidar: LidarSpec = LidarSpec()
    cameras: tuple[str, ...] = CAMERA_NAMES
    camera_hz: float = Field(30.0, description="30 / camera_hz must be an integer")
    image_width: int | None = Field(None, description="scale every camera to this width")
    png_compression: int = Field(1, ge=0, le=9)
    workers: int = Field(2, ge=1, description="threads encoding PNGs (output is identical)")
    # Calibration errors in what /tf_static publishes (truth keeps the real ones).
    lidar_ext_trans_err_m: float = 0.15
    lidar_ext_rot_err_deg: float = 0.4
    cam_ext_trans_err_m: float = 0.0
    cam_ext_rot_err_deg: float = 0.0
    # INS / GNSS / IMU errors.
    ins_bias_m: float = Field(0.15, description="constant position bias magnitude per agent")
    ins_bias_drift_m: float = Field(0.05, description="amplitude of the slow bias wander")
    ins_bias_period_s: float = 300.0
    ins_att_bias_deg: float = Field(0.02, description="constant attitude bias per axis")
    ins_noise_m: float = Field(0.0, description="white position noise of the INS output")
    gnss_noise_m: float = 0.02
    imu_gyro_noise: float = 1e-4
    imu_accel_noise: float = 0.01
    lidar_ext_err_agents: tuple[str, ...] | None = Field(
        None, description="agents whose published LiDAR extrinsic carries the error above "
                          "(None: every agent; the others publish the true one)")
    ins_drift_mps: float = Field(0.0, ge=0.0, description="INS position drift rate per agent "
                                 "(m/s, a seeded horizontal direction): b(t) += v_d * t")
    ins_drift_agents: tuple[str, ...] | None = Field(
        None, description="agents whose INS drifts by ins_drift_mps (None: every vehicle); "
                          "the drift direction of each agent is drawn either way")
    lidar_ext_err_xyz_m: tuple[float, float, float] | None = Field(
        None, description="explicit LiDAR extrinsic error: published translation = true + this "
                          "(base_link axes, m); with lidar_ext_err_rpy_deg replaces the "
                          "random-direction magnitudes above (see rig)")
    lidar_ext_err_rpy_deg: tuple[float, float, float] | None = Field(
        None, description="explicit LiDAR extrinsic rotation error roll, pitch, yaw (deg): "
                          "R_pub = Rz(yaw) Ry(pitch) Rx(roll) @ R_true")
    lidar_height_m: float | None = Field(
        None, gt=0.0, description="height of the vehicles' LiDAR origin above the ground "
                                  "(nominal mount, before the seeded mm-level mounting "
                                  "deviation); None: 1.55 m above base_link = 1.95 m")
    ins_step_m: tuple[float, float, float] | None = Field(
        None, description="a sudden INS position jump (world ENU axes, m) added to the "
                          "reported position from ins_step_at_s on, on ins_step_agents")
    ins_step_at_s: float = Field(1.0, description="clip time (s) of the INS step")
    ins_step_agents: tuple[str, ...] = Field(("black",), description="agents with the INS step")
    write_lidar_truth: bool = True
    radar: bool = Field(False, description="a 20 Hz front 4D radar on each vehicle "
                        "(simulate.radar)")
    side_lidar: bool = Field(False, description="a second LiDAR on each vehicle (issue #27): "
                             "LIDAR_LEFT, sparse, mounted on the left and tilted down towards "
                             "the near field, published with side_lidar_err_*; off: nothing "
                             "else in the clip changes")
    side_lidar_spec: LidarSpec = LidarSpec(beams=16, columns=600, dual_return=False,
                                           max_range_m=60.0, elev_min_deg=-15.0,
                                           elev_max_deg=15.0)
    side_lidar_mount_rpy_deg: tuple[float, float, float] = Field(
        (-40.0, 0.0, 90.0), description="true mounting of LIDAR_LEFT in base_link (roll pitch "
        "yaw, deg, R = Rz Ry Rx): facing left, rolled 40 deg down")
    side_lidar_mount_xyz_m: tuple[float, float, float] = (1.0, 0.9, 1.3)
    side_lidar_err_rpy_deg: tuple[float, float, float] = Field(
        (0.0, 0.0, 30.0), description="published LIDAR_LEFT rotation error (as "
        "lidar_ext_err_rpy_deg); the real lidar2lidar rig's is ~45 deg")
    side_lidar_err_xyz_m: tuple[float, float, float] = (0.05, -0.06, 0.04)
    pose_format: Literal["inspva", "odometry", "navsat-imu", "tf"] = Field(
        "inspva", description="how the vehicles' INS solution is written (simulate.navformats)")
    speed_mps: float = Field(18.0, description="nominal speed of the red agent")
    street: Literal["town", "corridor", "boulevard"] = Field(
        "town", description="town: mixed buildings, fences, parked cars, a few road users; "
                            "corridor: the hard street of issue #13; boulevard: the "
                            "cooperative scenario of issue #21 (see the module doc)")
    turn_at_s: float | None = Field(None, description="corridor: clip time (s) of the middle of "
                                                      "the 90 deg turn (default: mid-clip); "
                                                      "boulevard: of red's first turn "
                                                      "(default 1.0 s)")
    # boulevard (issue #21): every number of the scenario, so variations are overrides
    turn_rate_radps: float = Field(0.25, description="boulevard: red's yaw rate in its turn "
                                   "(rad/s, + = left; 0 = no turn at all)")
    turn_duration_s: float = Field(1.0, gt=0.0, description="boulevard: length of the turn "
                                   "(the logistic window integrates to rate * duration)")
    turn_ramp_s: float = Field(0.05, gt=0.0, description="boulevard: logistic on/off ramp "
                               "time constant of the turn (0.05 s: over 98 % of the rate "
                               "for the middle 0.6 s of a 1 s turn)")
    turn_back_after_s: float | None = Field(
        2.0, description="boulevard: red turns back (-rate for the same duration) this long "
                         "after the first turn (middle to middle), if the clip holds the whole "
                         "turn back and its ramp (5 turn_ramp_s); None: never")
    coop_gap_m: float = Field(-20.0, description="boulevard: black's position along the road "
                              "relative to red at clip time 0 (m, - behind, + ahead)")
    coop_speed_mps: float = Field(16.0, ge=0.0, description="boulevard: black's (constant) "
                                  "speed; it drives straight along its lane")
    coop_lane_m: float = Field(-5.25, description="boulevard: black's lane centre, left of the "
                               "road centre line (m)")
    red_lane_m: float | None = Field(
        None, description="boulevard: red's lane centre at clip time 0, left of the road centre "
                          "line; None: the lane right of black's for a left turn (or none), "
                          "left of it for a right turn, so red's turn crosses black's lane")
    wall_offset_m: float = Field(14.0, gt=0.0, description="boulevard: the walls' faces, "
                                 "left and right of the road centre line (m)")
    n_poles: int = Field(20, ge=0, description="boulevard: poles (both sidewalks)")
    n_parked_cars: int = Field(6, ge=0, description="boulevard: parked cars (right kerb)")

    @field_validator("agents")
    @classmethod
    def _agents(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        bad = [a for a in v if a not in AGENT_NAMES]
        if bad or "red" not in v or len(set(v)) != len(v):
            raise ValueError(
                f"agents must be distinct names from {AGENT_NAMES} incl. 'red', got {v}")
        return tuple(a for a in AGENT_NAMES if a in v)

    @field_validator("cameras")
    @classmethod
    def _cameras(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        bad = [c for c in v if c not in CAMERA_NAMES]
        if bad:
            raise ValueError(f"unknown cameras {bad}; choose from {CAMERA_NAMES}")
        return tuple(c for c in CAMERA_NAMES if c in v)

    @field_validator("ins_step_agents", "ins_drift_agents")
    @classmethod
    def _error_agents(cls, v: tuple[str, ...] | None) -> tuple[str, ...] | None:
        bad = [a for a in v or () if a not in AGENT_NAMES]
        if bad:
            raise ValueError(f"unknown agents {bad}; choose from {AGENT_NAMES}")
        return v

    @field_validator("camera_hz")
    @classmethod
    def _camera_hz(cls, v: float) -> float:
        div = 30.0 / v
        if v <= 0 or abs(div - round(div)) > 1e-9:
            raise ValueError(f"camera_hz must divide 30 (30, 15, 10, 6, 5, ...), got {v}")
        return v

    @property
    def name(self) -> str:
        return self.clip_id or f"sim_{self.preset_name}_s{self.seed}"

    @property
    def camera_step(self) -> int:
        """Render every n-th frame of the 30 Hz trigger grid."""
        return round(30.0 / self.camera_hz)

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> SimConfig:
        """``small`` (test scale), ``street``, ``coop`` or ``cats`` (Tab. 2); ``None`` overrides
        are ignored."""
        over = {k: v for k, v in overrides.items() if v is not None}
        if isinstance(over.get("agents"), str):
            over["agents"] = tuple(a.strip() for a in over["agents"].split(",") if a.strip())
        if isinstance(over.get("cameras"), str):
            cams = over["cameras"].strip()
            over["cameras"] = (
                CAMERA_NAMES[: max(1, int(cams))] if cams.isdigit()
                else tuple(c.strip() for c in cams.split(",") if c.strip())
            )
        if name == "cats":
            base: dict[str, Any] = {
                "preset_name": "cats", "lidar": LidarSpec(), "cameras": CAMERA_NAMES,
                "image_width": None, "write_lidar_truth": False,
            }
        elif name == "small":
            base = {
                "preset_name": "small",
                "lidar": LidarSpec(beams=32, columns=360, dual_return=False, max_range_m=120.0),
                "cameras": CAMERA_NAMES, "image_width": 640,
                "write_lidar_truth": True,
            }
        elif name == "street":
            base = {
                "preset_name": "street",
                "lidar": LidarSpec(beams=32, columns=360, dual_return=False, max_range_m=120.0),
                "cameras": (), "image_width": 640, "write_lidar_truth": True,
                "street": "corridor", "speed_mps": 10.0, "lidar_ext_trans_err_m": 0.15,
                "lidar_ext_rot_err_deg": 0.4, "lidar_ext_err_agents": ("black",),
                "ins_drift_mps": 0.03,
            }
        elif name == "coop":
            base = {
                "preset_name": "coop",
                "lidar": LidarSpec(beams=64, columns=1024, dual_return=False, max_range_m=200.0),
                "cameras": (), "image_width": 640, "write_lidar_truth": True,
                "street": "boulevard", "speed_mps": 15.0, "lidar_height_m": 1.9,
                "lidar_ext_err_agents": ("black",), "lidar_ext_err_xyz_m": (0.12, -0.08, 0.05),
                "lidar_ext_err_rpy_deg": (0.0, 0.0, 0.4),
                "ins_bias_m": 0.0, "ins_bias_drift_m": 0.0, "ins_att_bias_deg": 0.0,
                "ins_noise_m": 0.0, "ins_drift_mps": 0.0, "pose_format": "odometry",
            }
        else:
            raise ValueError(
                f"unknown preset {name!r}; choose 'small', 'street', 'coop' or 'cats'")
        base.update(over)
        return cls(**base)
