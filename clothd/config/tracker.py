"""The tracker's sections of the configuration tree (`tracker:` in config.yaml)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from clothd.config.strict import Strict


class IdealCameraConfig(Strict):
    """Used when footage comes without camera.json: principal point at the image centre, table parallel
    to the image plane at `distance_m`."""

    f_px: float = Field(900.0, gt=10, le=20000)
    distance_m: float = Field(1.0, gt=0.05, le=20)
    width_px: int = Field(640, ge=64, le=8192, description="the live camera's image size")
    height_px: int = Field(480, ge=64, le=8192)


class FeatureConfig(Strict):
    max_features: int = Field(600, ge=10, le=5000, description="about what the default cloth offers")
    quality_level: float = Field(0.01, gt=0, le=1, description="Shi-Tomasi, relative to the best corner")
    min_distance_px: float = Field(5.0, ge=1, le=100)
    block_size_px: int = Field(5, ge=3, le=31)
    lk_window_px: int = Field(11, ge=5, le=63)
    lk_levels: int = Field(1, ge=0, le=6, description="pyramid levels above the base")
    lk_max_iterations: int = Field(20, ge=1, le=200)
    lk_epsilon_px: float = Field(0.01, gt=0, le=1)
    fb_max_error_px: float = Field(0.5, gt=0, le=20, description="forward-backward check threshold")
    # A patch that is still itself one frame later correlates >= 0.75 in hwsim footage, across the compress
    # fold's shading and the random scenario's motion blur (median ~0.96); a patch replaced by noise
    # correlates <= 0.5. The default lies between.
    lk_min_ncc: float = Field(0.6, ge=-1, le=1, description="the LK window must still correlate this well")
    ncc_window_px: int = Field(9, ge=3, le=63, description="the centre of the LK window that NCC compares")
    # LK's covariance is sigma² G⁻¹: along a wale (an edge in the patch) a measurement says little. Above 1,
    # the estimator takes each feature's R from its structure tensor, its weak side at most this many times
    # the variance of its strong side, and the forward-backward check looks across the edge only
    # (clothd/core/features.py). 1 (off) on a cloth with corners, where it changes nothing for the better.
    aperture_max_ratio: float = Field(
        1.0, ge=1, le=1e6, description="largest variance ratio of a measurement's weak to strong axis"
    )
    # A periodic weave (a plain twill: stripes, no corners) tells itself at the start: the median λ1/λ2 of
    # the structure tensors of the first features is ~70-90 on hwsim's twill and ~4 on its denim. On such
    # a cloth LK takes periodic_lk_window_px, each measurement counts across the stripes only (its
    # aperture ratio capped at periodic_aperture_max_ratio), the mesh holds its shape (EkfConfig.
    # periodic_shape_sigma_m), and the outline becomes a measurement (clothd/core/outline_edges.py): the
    # edge searched for across the mesh's border at outline_per_side points a side (0: never), within
    # outline_search_px of the estimate. docs/architecture.md, "Periodic weaves".
    periodic_ratio: float = Field(20.0, ge=1, le=1e9, description="median λ1/λ2 that marks a periodic weave")
    periodic_lk_window_px: int = Field(15, ge=5, le=63, description="LK window on a periodic weave")
    periodic_aperture_max_ratio: float = Field(
        1000.0, ge=1, le=1e6, description="aperture_max_ratio on a periodic weave"
    )
    outline_per_side: int = Field(160, ge=0, le=200, description="edge points on each side of the mesh")
    outline_search_px: float = Field(4.0, gt=0, le=50, description="how far across the outline to search")
    # A repeating pattern with corners (a check) tells itself at the start too: the median best match of
    # the first features' windows with the same windows moved 3-8 px (features.self_similarity) reaches
    # repetitive_ncc (hwsim's gingham 0.94-0.96, denim ~0.62). There LK takes repetitive_lk_levels (a
    # coarser level halves a 5.4 px check to the Nyquist limit, where LK lands on look-alikes even from
    # a start 0.8 px off), the mesh holds its shape as on a periodic weave, every feature is also tracked
    # from where it was, and where that and the prediction's start land on different look-alikes the
    # cloth the other features place decides (clothd/core/tracker.py). Above 1: never.
    repetitive_ncc: float = Field(
        0.85, gt=0, le=2, description="self-similarity that marks a repeating pattern"
    )
    repetitive_lk_levels: int = Field(0, ge=0, le=6, description="LK pyramid levels on a repeating pattern")
    resample_below_fraction: float = Field(0.7, gt=0, le=1, description="of max_features")
    resample_cell_px: int = Field(48, ge=8, le=640, description="a cell of the cloth with no feature")
    edge_margin_px: float = Field(6.0, ge=0, le=100, description="keep new features this far inside")
    # Drift correction (clothd/core/anchors.py): every frame-to-frame result refined from its anchor frame.
    anchor: bool = Field(True, description="hold each feature to its appearance in an anchor frame")
    anchor_max_px: float = Field(
        0.5, gt=0, le=10, description="the anchored and frame-to-frame positions must agree this well"
    )
    anchor_still_px: float = Field(
        1.0, gt=0, le=100, description="a feature this far off its anchor has moved: it is anchored anew"
    )
    anchor_adopt_frames: int = Field(15, ge=1, le=10000, description="anchor loose features this often")
    anchor_max_frames: int = Field(4, ge=1, le=64, description="anchor frames kept; past this, all re-anchor")


class MeshConfig(Strict):
    nodes_x: int = Field(12, ge=2, le=64)
    nodes_y: int = Field(12, ge=2, le=64)
    fold_tolerance_strain: float = Field(
        0.10, ge=0, lt=1, description="an edge this much shorter on the table than at rest has folded up"
    )


class PhysicsConfig(Strict):
    """The tracker's own cloth model: a Provot mass-spring on the tracking mesh."""

    areal_density_kg_m2: float = Field(0.40, gt=0.01, le=5)
    stretch_k_n_m: float = Field(50.0, gt=0, le=1e5, description="structural spring; Provot: soft + limited")
    shear_k_n_m: float = Field(10.0, gt=0, le=1e5)
    flexion_k_n_m: float = Field(2.0, ge=0, le=1e5)
    damping_1_s: float = Field(8.0, ge=0, le=1000, description="velocity damping relative to the belt")
    friction_mu: float = Field(1.0, gt=0, le=3)
    stick_speed_m_s: float = Field(0.002, gt=0, le=0.1)
    strain_limit: float = Field(0.05, gt=0, le=1, description="Provot: springs never stretch past this")
    slack_strain: float = Field(
        0.04, ge=0, lt=1, description="springs pull only past this strain (a woven fabric's crimp)"
    )
    compression_k_ratio: float = Field(
        0.05, ge=0, le=1, description="a compressed spring's share of its stiffness: cloth buckles instead"
    )
    substeps: int = Field(20, ge=1, le=500)

    @model_validator(mode="after")
    def _slack_below_limit(self) -> PhysicsConfig:
        if self.slack_strain >= self.strain_limit:
            raise ValueError(
                f"slack_strain ({self.slack_strain}) must be below strain_limit ({self.strain_limit})"
            )
        return self


class EkfConfig(Strict):
    meas_sigma_px: float = Field(0.7, gt=0, le=50)
    # A frame exposed for exposure_s up to its time stamp shows a moving cloth smeared over that time, and
    # LK finds the smear's middle: the measurement model of the mesh EKF places it where the nodes were
    # exposure_s / 2 earlier (p - v exposure_s / 2). 0: the frame is an instant (estimators/mesh.py).
    exposure_s: float = Field(0.0, ge=0, le=0.1, description="the camera's exposure, ending at the frame")
    process_pos_sigma_m: float = Field(0.0005, gt=0, le=1, description="per tick")
    process_vel_sigma_m_s: float = Field(0.01, gt=0, le=10, description="per tick")
    initial_pos_sigma_m: float = Field(0.002, gt=0, le=1)
    initial_vel_sigma_m_s: float = Field(0.01, gt=0, le=10)
    gate_chi2: float = Field(13.8, gt=0, le=1000, description="Mahalanobis gate, 2 dof (13.8 = 99.9 %)")
    smoothness_sigma_m: float = Field(
        0.005, gt=0, le=1, description="how far the corrections of neighbouring mesh nodes may differ"
    )
    # On a periodic weave the features measure across the stripes only, and nothing inside the cloth says
    # where along them it lies: every mesh edge (sides and diagonals) is held to its rest length within
    # this while stretched, 3x more loosely while compressed (cloth buckles into folds). A repeating
    # pattern (FeatureConfig.repetitive_ncc) is held the same way. 0: never.
    periodic_shape_sigma_m: float = Field(
        0.0002, ge=0, le=0.1, description="how closely a periodic weave's mesh edges keep their rest length"
    )
    divergence_nis: float = Field(50.0, gt=0, le=1e6, description="mean NIS per measurement that means lost")


class ModuleLimitsConfig(Strict):
    """The steppers' limits, so the model's input is what the modules do, not only what they were told."""

    accel_limit_m_s2: float = Field(2.0, gt=0, le=50)
    steer_rate_limit_rad_s: float = Field(3.0, gt=0, le=100)


class StereoConfig(Strict):
    """A second camera's view, used when tracking begins to measure the surface (clothd/core/stereo.py)."""

    max_skew_ms: float = Field(
        20.0, ge=0, le=200, description="two frames further apart in capture time than this are not paired"
    )
    epipolar_max_px: float = Field(
        1.5, gt=0, le=20, description="a match this far off its epipolar line is a wrong match"
    )
    max_height_m: float = Field(
        0.05, gt=0, le=0.5, description="the highest the cloth can rise: bounds the search along the line"
    )
    min_matches: int = Field(
        30, ge=4, le=10000, description="fewer matches than this and the surface is not measured (mono)"
    )


class TaichiConfig(Strict):
    arch: Literal["cpu", "cuda", "vulkan"] = "cpu"


class TrackerConfig(Strict):
    model: Literal["none", "predict", "rigid", "mesh"] = "mesh"
    use_input: bool = True
    camera: IdealCameraConfig = IdealCameraConfig()
    modules: ModuleLimitsConfig = ModuleLimitsConfig()
    features: FeatureConfig = FeatureConfig()
    mesh: MeshConfig = MeshConfig()
    physics: PhysicsConfig = PhysicsConfig()
    ekf: EkfConfig = EkfConfig()
    stereo: StereoConfig = StereoConfig()

    @property
    def estimates_shape(self) -> bool:
        """The model tracks the cloth's shape (a mesh of its own), so flatness can be read off it."""
        return self.model in ("mesh", "predict")
