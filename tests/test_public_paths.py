"""Every import path that the README, docs/accepts.md, the guide, the examples, the benchmarks
and the tests used before the modules moved into folders by layer still imports: each
module, and each name reached through it (the paths were listed from those files; a moved
module's old path is a module of re-exports, e.g. ``jaximu/so3.py``)."""

import importlib
import types

import pytest

PATHS = {
    "jaximu": ("jaximu",),
    "ImuBias": ("jaximu.ImuBias",),
    "ImuNoise": ("jaximu.ImuNoise",),
    "NavState": ("jaximu.NavState",),
    "SensorPose": ("jaximu.SensorPose",),
    "allan": (
        "jaximu.allan",
        "jaximu.allan.allan_deviation",
        "jaximu.allan.check_units",
        "jaximu.allan.fit_noise",
        "jaximu.allan.motion_ratio",
        "jaximu.allan.static_intervals",
    ),
    "app": ("jaximu.app.main",),
    "bias_jacobians_autodiff": ("jaximu.bias_jacobians_autodiff",),
    "boxminus": ("jaximu.boxminus",),
    "boxplus": ("jaximu.boxplus",),
    "calibration": (
        "jaximu.calibration",
        "jaximu.calibration.calibrate",
        "jaximu.calibration.calibration_loss",
        "jaximu.calibration.calibration_problem",
        "jaximu.calibration.calibration_residuals",
        "jaximu.calibration.noise_table",
    ),
    "cli": (
        "jaximu.cli",
        "jaximu.cli.main",
        "jaximu.cli.options_table",
    ),
    "compose": ("jaximu.compose",),
    "correct": ("jaximu.correct",),
    "datasets": (
        "jaximu.datasets",
        "jaximu.datasets.euroc_v1_02_segment",
    ),
    "discrete_process_noise": ("jaximu.discrete_process_noise",),
    "earth_rate": ("jaximu.earth_rate",),
    "ekf_update": ("jaximu.ekf_update",),
    "errors": (
        "jaximu.errors",
        "jaximu.errors.Fix",
        "jaximu.errors.InputError",
    ),
    "errorstate": (
        "jaximu.errorstate.blocks_autodiff",
        "jaximu.errorstate.dense_from_blocks",
        "jaximu.errorstate.ekf_update",
        "jaximu.errorstate.jacobians_autodiff",
        "jaximu.errorstate.position_jacobian",
    ),
    "integrators": (
        "jaximu.integrators.get_attitude",
        "jaximu.integrators.nav_step",
    ),
    "io": (
        "jaximu.io",
        "jaximu.io.DataError",
        "jaximu.io.from_arrays",
        "jaximu.io.gravity_alignment",
        "jaximu.io.initial_state",
        "jaximu.io.read_csv",
        "jaximu.io.read_euroc",
        "jaximu.io.read_npz",
        "jaximu.io.read_rosbag",
        "jaximu.io.read_states",
        "jaximu.io.read_tum",
        "jaximu.io.read_tumvi",
        "jaximu.io.trajectory_errors",
        "jaximu.io.validate_imu",
        "jaximu.io.write_states",
        "jaximu.io.write_tum",
    ),
    "kalibr": (
        "jaximu.kalibr",
        "jaximu.kalibr.read_sensor_yaml",
        "jaximu.kalibr.write_imu_yaml",
    ),
    "keyframes": (
        "jaximu.keyframes",
        "jaximu.keyframes.groundtruth_coverage",
        "jaximu.keyframes.groundtruth_residuals",
        "jaximu.keyframes.keyframe_windows",
    ),
    "learning": (
        "jaximu.learning",
        "jaximu.learning.Denoiser",
        "jaximu.learning.ModelConfig",
        "jaximu.learning.Sequence",
        "jaximu.learning.TrainConfig",
        "jaximu.learning.attitude_covariance",
        "jaximu.learning.evaluate_sequence",
        "jaximu.learning.evaluation.attitude_terms",
        "jaximu.learning.integrate_attitude",
        "jaximu.learning.load",
        "jaximu.learning.load_sequence",
        "jaximu.learning.losses",
        "jaximu.learning.losses.increment_loss",
        "jaximu.learning.losses.rotation_step_blocks",
        "jaximu.learning.orientation_errors",
        "jaximu.learning.pretrained",
        "jaximu.learning.save",
        "jaximu.learning.split",
        "jaximu.learning.train",
        "jaximu.learning.training",
        "jaximu.learning.uncertainty",
    ),
    "montecarlo": (
        "jaximu.montecarlo",
        "jaximu.montecarlo.MonteCarloResult",
        "jaximu.montecarlo.PositionFix",
        "jaximu.montecarlo.chi2_interval",
        "jaximu.montecarlo.load_result",
        "jaximu.montecarlo.monte_carlo",
        "jaximu.montecarlo.sample_run",
    ),
    "needs_reintegration": ("jaximu.needs_reintegration",),
    "plots": ("jaximu.plots",),
    "predict": ("jaximu.predict",),
    "preintegrate": ("jaximu.preintegrate",),
    "preintegration": ("jaximu.preintegration.ImuBias",),
    "propagate": (
        "jaximu.propagate",
        "jaximu.propagate.sensor_engine_inputs",
    ),
    "propagate_covariance": ("jaximu.propagate_covariance",),
    "propagate_covariance_final": ("jaximu.propagate_covariance_final",),
    "propagate_final": ("jaximu.propagate_final",),
    "recording": (
        "jaximu.recording",
        "jaximu.recording.default_P0",
        "jaximu.recording.noise_preset",
        "jaximu.recording.propagate_recording",
        "jaximu.recording.run_demo",
    ),
    "residual": ("jaximu.residual",),
    "sensor": (
        "jaximu.sensor",
        "jaximu.sensor.SensorPose",
        "jaximu.sensor.chunk_to_body",
    ),
    "simulate": (
        "jaximu.simulate",
        "jaximu.simulate.add_noise",
        "jaximu.simulate.circle",
        "jaximu.simulate.figure_eight",
        "jaximu.simulate.helix",
        "jaximu.simulate.ideal_imu",
        "jaximu.simulate.lissajous",
        "jaximu.simulate.true_states",
        "jaximu.simulate.waypoints",
    ),
    "so3": (
        "jaximu.so3",
        "jaximu.so3.euler_rate_matrix",
        "jaximu.so3.euler_zyx_to_matrix",
        "jaximu.so3.euler_zyx_to_quat",
        "jaximu.so3.exp",
        "jaximu.so3.exp_matrix",
        "jaximu.so3.hamilton_to_jpl",
        "jaximu.so3.jpl_to_hamilton",
        "jaximu.so3.left_jacobian",
        "jaximu.so3.log",
        "jaximu.so3.log_matrix",
        "jaximu.so3.matrix_to_quat",
        "jaximu.so3.quat_conj",
        "jaximu.so3.quat_first_order_update",
        "jaximu.so3.quat_identity",
        "jaximu.so3.quat_mul",
        "jaximu.so3.quat_normalize",
        "jaximu.so3.quat_rotate",
        "jaximu.so3.quat_to_euler_zyx",
        "jaximu.so3.quat_to_matrix",
        "jaximu.so3.right_jacobian",
        "jaximu.so3.right_jacobian_inv",
        "jaximu.so3.skew",
        "jaximu.so3.wxyz_to_xyzw",
        "jaximu.so3.xyzw_to_wxyz",
    ),
    "state": (
        "jaximu.state.BA",
        "jaximu.state.BG",
        "jaximu.state.NavState",
        "jaximu.state.POS",
        "jaximu.state.THETA",
        "jaximu.state.VEL",
        "jaximu.state.boxminus",
        "jaximu.state.boxplus",
    ),
    "step_jacobians": ("jaximu.step_jacobians",),
    "whitened_residual": ("jaximu.whitened_residual",),
    "world": ("jaximu.world",),
}


def resolve(path):
    """Reach a dotted ``path`` as user code does: attributes of what is imported; the module
    of that name where the attribute is not one that leads on (``jaximu.propagate`` is the
    function, ``from jaximu.propagate import x`` the module). Importing first would rebind a
    name such as ``jaximu.learning.pretrained``, a function, to a folder of that name."""
    parts = path.split(".")
    obj = importlib.import_module(parts[0])
    for i in range(1, len(parts)):
        attr = getattr(obj, parts[i], None)
        leads_on = i + 1 == len(parts) or hasattr(attr, parts[i + 1])
        if attr is None or not (isinstance(attr, types.ModuleType) or leads_on):
            attr = importlib.import_module(".".join(parts[: i + 1]))
        obj = attr
    return obj


@pytest.mark.parametrize("group", sorted(PATHS))
def test_public_paths_import(group):
    if group == "learning":
        pytest.importorskip("equinox")
    missing = []
    for path in PATHS[group]:
        try:
            resolve(path)
        except (ImportError, AttributeError) as e:
            missing.append(f"{path}: {e}")
    assert not missing, "\n".join(missing)


def test_old_and_new_paths_are_the_same_objects():
    """A moved module's old path gives the objects of its new home, private names included."""
    import jaximu
    import jaximu.errorstate
    import jaximu.so3
    from jaximu.engine import errorstate, jacobians, update
    from jaximu.geometry import so3

    assert (
        jaximu.so3.exp is so3.exp
        and jaximu.errorstate.position_jacobian is update.position_jacobian
    )
    assert jaximu.errorstate._check_cov is errorstate._check_cov
    assert jaximu.errorstate.blocks_autodiff is jacobians.blocks_autodiff
    assert callable(jaximu.propagate)  # the function, as before (not the module of that name)
