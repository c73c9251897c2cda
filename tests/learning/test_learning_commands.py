"""``jaximu learn train|evaluate`` end to end on sequence folders written in EuRoC's flat
layout, and the bad inputs a user brings: each ends with one line naming the argument and
the fix, exit code 2, and nothing written or overwritten."""

from __future__ import annotations

import dataclasses
import json

import jax
import numpy as np
import pytest
from test_learning_losses import scipy_attitudes, smooth_rates

from jaximu import cli, learning
from jaximu.io import DataError
from jaximu.learning import Denoiser, ModelConfig

# without the bias tracker: the untrained model is then the constant-bias baseline exactly
# (and the written recordings' accelerometer does not turn with their gyro)
TINY = ModelConfig(channels=(4, 4), kernel=3, dilations=(1, 2), bias_tracking=False)


def write_sequence(
    folder, seconds=12.0, rate=200.0, gt_shift=0.0, nan_row=None, seed=0, gt_gap=None
):
    """A recording in the flat layout (``imu.csv`` + full-state ``groundtruth.csv``);
    ``gt_gap``: ``(start, stop)`` [s] whose ground-truth rows are left out (a mocap dropout)."""
    rng = np.random.default_rng(seed)
    dt = 1.0 / rate
    T = int(seconds * rate)
    w = smooth_rates(rng, T) * 0.5
    q, _ = scipy_attitudes(np.array([1.0, 0.0, 0.0, 0.0]), w, dt)
    gyro = w + np.array([-0.002, 0.021, 0.077])
    accel = np.tile([0.0, 0.0, 9.81], (T, 1)) + 0.02 * rng.standard_normal((T, 3))
    if nan_row is not None:
        gyro[nan_row, 1] = np.nan
    stamps = 1_403_715_523_912_143_104 + np.round(np.arange(T) * dt * 1e9).astype(np.int64)
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / "imu.csv", "w") as f:
        f.write("#timestamp [ns],w_x,w_y,w_z,a_x,a_y,a_z\n")
        for s, g, a in zip(stamps, gyro, accel):
            f.write(f"{s}," + ",".join(f"{x:.17g}" for x in (*g, *a)) + "\n")
    gt_stamps = stamps + int(gt_shift * 1e9)
    keep = np.ones(T, bool)
    if gt_gap is not None:
        keep[int(gt_gap[0] * rate) : int(gt_gap[1] * rate)] = False
    z = np.zeros(3)
    with open(folder / "groundtruth.csv", "w") as f:
        f.write("#timestamp,px,py,pz,qw,qx,qy,qz,vx,vy,vz,bgx,bgy,bgz,bax,bay,baz\n")
        for s, qq in zip(gt_stamps[keep], q[keep]):
            vals = (*z, *qq, *z, -0.002, 0.021, 0.077, *z)
            f.write(f"{s}," + ",".join(f"{x:.17g}" for x in vals) + "\n")
    return folder


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    root = tmp_path_factory.mktemp("learn")
    model = learning.save(root / "model", Denoiser(TINY, jax.random.key(0)), {"seed": 0})
    return {"root": root, "model": model, "seq": write_sequence(root / "seq")}


def run(capsys, *argv):
    code = cli.main(list(argv))
    out = capsys.readouterr()
    return code, out.out, out.err


def evaluate_with_outputs(capsys, folders, js, plot):
    """``jaximu learn evaluate`` of the untrained model on the written sequence."""
    model, seq = str(folders["model"]), str(folders["seq"])
    return run(capsys, "learn", "evaluate", model, seq, "--json", str(js), "--plot", str(plot))


def test_evaluate_prints_the_three_ways_and_writes_json_and_plot(folders, capsys, tmp_path):
    js, png = tmp_path / "eval.json", tmp_path / "eval.png"
    code, out, err = evaluate_with_outputs(capsys, folders, js, png)
    assert code == 0, err
    assert "constant bias" in out and "NEES" in out
    doc = json.loads(js.read_text())
    (s,) = doc["sequences"]
    assert s["name"] == "seq" and s["samples"] == 2400
    for key in ("aoe_mean_deg", "aoe_rmse_deg", "aye_mean_deg"):
        assert set(s[key]) == {"raw", "constant_bias", "learned"}
    # the untrained model is the constant-bias baseline, and the bias is the model's (zero)
    assert s["aoe_mean_deg"]["learned"] == pytest.approx(
        s["aoe_mean_deg"]["constant_bias"], rel=1e-4
    )
    assert s["aoe_mean_deg"]["raw"] > 1.0
    assert 0.0 <= s["inside_3sigma"] <= 1.0 and s["nees_orientation"] > 0
    # the windowed NEES beside the whole run's, printed and written (12 s: 1-s and 5-s windows)
    assert "over windows from the true attitude 1s " in out
    assert set(s["window_nees_orientation"]) == {"1s", "5s"}
    assert all(x > 0 for x in s["window_nees_orientation"].values())
    assert png.stat().st_size > 10_000


def test_train_writes_a_model_that_evaluates(folders, capsys):
    seq = write_sequence(folders["root"] / "long", seconds=84.0, seed=1)
    out_model = folders["root"] / "trained"
    code, out, err = run(
        capsys,
        "learn",
        "train",
        str(seq),
        "--out",
        str(out_model),
        "--steps",
        "1",
        "--seed",
        "3",
        "--bias-markov",
        "--velocity-sigma",
        "2.5",
        "--learning-rate",
        "0.001",
        "--validate-every",
        "5",
        "--align-reference",
    )
    assert code == 0, err
    assert "validation" in out and "compile" in out
    meta = json.loads((out_model / "model.json").read_text())
    assert meta["record"]["seed"] == 3 and meta["record"]["command"].startswith("jaximu learn")
    assert meta["record"]["command"].endswith(
        "--velocity-sigma 2.5 --bias-markov --align-reference"
    )
    # the written ground truth is on the IMU's stamps: no clock offset to realign
    (offset,) = meta["record"]["reference_offsets_s"].values()
    assert abs(offset) < 5e-4
    assert meta["config"]["velocity_sigma"] == 2.5  # the tracker's bound, as passed
    assert "--steps 1 --learning-rate 0.001 --validate-every 5 " in meta["record"]["command"]
    train = meta["record"]["train"]
    assert (train["learning_rate"], train["validate_every"]) == (0.001, 5)
    assert train["min_learning_rate"] == pytest.approx(1e-4)  # annealed to a tenth
    # the validation part's (4 s) windowed NEES, before and with the Gauss–Markov bias fitted
    # on it, which the saved model keeps
    u = meta["record"]["uncertainty"]
    assert set(u["validation_window_nees"]["long"]) == {"1s"}
    assert u["validation_window_nees_markov"]["long"]["1s"] > 0
    loaded = learning.load(out_model)
    assert loaded.config.rate_hz == pytest.approx(200.0)
    assert loaded.config.bias_markov == (u["bias_markov_sigma"], u["bias_markov_time"])


def one_line_error(code, err, *needles):
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    for n in needles:
        assert n in lines[0], lines[0]


def test_a_folder_that_is_not_a_sequence(folders, capsys, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    code, _, err = run(capsys, "learn", "train", str(empty), "--out", str(tmp_path / "m"))
    one_line_error(code, err, str(empty), "imu.csv")
    assert not (tmp_path / "m").exists()
    code, _, err = run(capsys, "learn", "evaluate", str(folders["model"]), str(empty))
    one_line_error(code, err, str(empty))


def test_an_output_that_is_a_file_is_not_overwritten(folders, capsys, tmp_path):
    f = tmp_path / "keep.txt"
    f.write_text("mine")
    code, _, err = run(capsys, "learn", "train", str(folders["seq"]), "--out", str(f))
    one_line_error(code, err, "--out", str(f))
    assert f.read_text() == "mine"
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    code, _, err = run(capsys, "learn", "train", str(folders["seq"]), "--out", str(other))
    one_line_error(code, err, "--out", "not a jaximu model")
    code, _, err = run(
        capsys,
        "learn",
        "evaluate",
        str(folders["model"]),
        str(folders["seq"]),
        "--json",
        str(tmp_path / "missing" / "x.json"),
    )
    one_line_error(code, err, "--json", "does not exist")


def test_a_model_that_is_not_one(folders, capsys, tmp_path):
    code, _, err = run(capsys, "learn", "evaluate", str(folders["seq"]), str(folders["seq"]))
    one_line_error(code, err, "is not a jaximu model", "model.json")
    bad = tmp_path / "old"
    bad.mkdir()
    (bad / "weights.eqx").write_bytes(b"\0" * 10)
    (bad / "model.json").write_text(json.dumps({"format": "jaximu.learning.Denoiser/0"}))
    code, _, err = run(capsys, "learn", "evaluate", str(bad), str(folders["seq"]))
    one_line_error(code, err, "format", "retrain")
    (bad / "model.json").write_text(
        json.dumps({"format": learning.checkpoint.FORMAT, "config": TINY.to_json()})
    )
    code, _, err = run(capsys, "learn", "evaluate", str(bad), str(folders["seq"]))
    one_line_error(code, err, "weights.eqx", "damaged")


def test_a_model_folder_named_like_the_shipped_model_is_the_one_read(
    folders, capsys, tmp_path, monkeypatch
):
    """``--out euroc`` (the shipped model's own command) then ``evaluate euroc`` in that
    folder reads the user's model, not the shipped one, and says which it read; elsewhere
    (or a folder ``euroc`` that is no model, such as a dataset's) the name is the shipped
    model's."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "euroc").mkdir()  # a dataset folder of that name: not a model
    assert learning.checkpoint.shipped("euroc")
    assert learning.load("euroc").config == learning.pretrained("euroc").config
    learning.save("euroc", learning.load(folders["model"]), {"seed": 0})
    assert not learning.checkpoint.shipped("euroc")
    assert learning.load("euroc").config == TINY
    assert learning.checkpoint.record("euroc") == {"seed": 0}
    assert learning.pretrained("euroc").config != TINY
    code, out, err = run(capsys, "learn", "evaluate", "euroc", str(folders["seq"]))
    assert code == 0, err
    assert out.startswith(f"model: euroc (the folder {tmp_path / 'euroc'})")


def test_one_folder_twice_is_refused_and_namesakes_are_named_by_their_paths(
    folders, capsys, tmp_path
):
    """The same folder twice (another spelling of it too) is refused before any work; two
    folders of one name are told apart by the paths given; from Python, two sequences of one
    name are refused by train (its record and leave-one-out figures are by name)."""
    seq = folders["seq"]
    out = tmp_path / "m"
    code, _, err = run(capsys, "learn", "train", str(seq), f"{seq}/../seq", "--out", str(out))
    one_line_error(code, err, "given twice")
    assert not out.exists()
    twin = write_sequence(tmp_path / "other" / seq.name, seconds=5.0)
    js = tmp_path / "x.json"
    code, _, err = run(
        capsys, "learn", "evaluate", str(folders["model"]), str(seq), str(twin), "--json", str(js)
    )
    assert code == 0, err
    assert [s["name"] for s in json.loads(js.read_text())["sequences"]] == [str(seq), str(twin)]
    one = learning.load_sequence(twin)
    with pytest.raises(DataError, match="distinct names; 'seq' is given more than once"):
        learning.train([one, one])


def test_a_sequence_at_another_rate(folders, capsys, tmp_path):
    seq = write_sequence(tmp_path / "slow", seconds=12.0, rate=100.0)
    code, _, err = run(capsys, "learn", "evaluate", str(folders["model"]), str(seq))
    one_line_error(code, err, "100.0 Hz", "200 Hz", "resample")


def test_ground_truth_that_does_not_cover_the_imu(folders, capsys, tmp_path):
    seq = write_sequence(tmp_path / "late", seconds=5.0, gt_shift=100.0)
    code, _, err = run(capsys, "learn", "evaluate", str(folders["model"]), str(seq))
    one_line_error(code, err, "does not cover")


def test_ground_truth_with_a_gap_is_compared_only_where_it_has_rows(folders, capsys, tmp_path):
    """A 0.2-s mocap dropout (40 rows at 200 Hz, beyond 5 × the median interval) is not
    refused: every IMU sample is integrated, the samples inside it have no reference, and
    the errors are measured at the 960 rows the ground truth has; ``--max-gap 0.5`` bridges
    it for the reference at the samples (the comparison stays at the rows)."""
    seq = write_sequence(tmp_path / "gap", seconds=5.0, gt_gap=(2.0, 2.2))
    js = tmp_path / "gap.json"
    argv = ("learn", "evaluate", str(folders["model"]), str(seq), "--json", str(js))
    code, out, err = run(capsys, *argv)
    assert code == 0, err
    assert "40 IMU samples fall in ground-truth dropouts (the longest 0.2" in out
    assert "compared at 960 ground-truth stamps" in out
    assert json.loads(js.read_text())["sequences"][0]["samples"] == 1000
    loaded = learning.load_sequence(seq)
    assert np.sum(~loaded.has_reference) == 40 and len(loaded.stamps()[0]) == 960
    code, out, err = run(capsys, *argv, "--max-gap", "0.5")
    assert code == 0, err
    assert "dropouts" not in out and "compared at 960" in out
    assert learning.load_sequence(seq, max_gap=0.5).reference is None
    code, _, err = run(capsys, *argv, "--max-gap", "-1")
    one_line_error(code, err, "--max-gap", "positive")
    with pytest.raises(ValueError, match="max_gap"):
        learning.load_sequence(seq, max_gap=-1.0)


def test_a_plot_format_matplotlib_cannot_write_is_refused_before_any_work(
    folders, capsys, tmp_path
):
    js, bad = tmp_path / "x.json", tmp_path / "errors.txt"
    code, _, err = evaluate_with_outputs(capsys, folders, js, bad)
    one_line_error(code, err, "--plot", ".png")
    assert not js.exists() and not bad.exists()


def test_nan_samples_are_refused_unless_dropped(folders, capsys, tmp_path):
    """NaN in row 100 (line 102): one line naming the folder, the line and
    ``--drop-nonfinite``; with it, the 999 others are evaluated and the repair reported."""
    seq = write_sequence(tmp_path / "nan", seconds=5.0, nan_row=100)
    js = tmp_path / "x.json"
    argv = ("learn", "evaluate", str(folders["model"]), str(seq), "--json", str(js))
    code, _, err = run(capsys, *argv)
    one_line_error(code, err, str(seq), "NaN", "line 102", "--drop-nonfinite")
    assert not js.exists()
    code, _, err = run(capsys, *argv, "--drop-nonfinite")
    assert code == 0, err
    assert json.loads(js.read_text())["sequences"][0]["samples"] == 999
    assert f"repair: {seq}: dropped 1" in err


def edit_imu_rows(folder, edit):
    """Rewrite ``folder/imu.csv`` with its data rows passed through ``edit``."""
    path = folder / "imu.csv"
    header, *rows = path.read_text().splitlines()
    path.write_text("\n".join([header, *edit(rows)]) + "\n")
    return folder


@pytest.mark.parametrize(
    "name, edit, needles, flag",
    [
        (
            "dup",
            lambda r: r[:100] + [r[99]] + r[100:],
            ("duplicate", "line 102"),
            "--drop-duplicates",
        ),
        ("back", lambda r: r[:99] + [r[100], r[99]] + r[101:], ("backwards", "line 102"), "--sort"),
        # an IMU gap: its flag here is --allow-gaps, not the command's --max-gap (the ground
        # truth's)
        ("imugap", lambda r: r[:300] + r[340:], ("0.205 s after line 301",), "--allow-gaps"),
    ],
)
def test_imu_rows_the_reader_repairs_are_refused_naming_the_folder_and_flag(
    folders, capsys, tmp_path, name, edit, needles, flag
):
    seq = edit_imu_rows(write_sequence(tmp_path / name, seconds=5.0), edit)
    argv = ("learn", "evaluate", str(folders["model"]), str(seq))
    code, _, err = run(capsys, *argv)
    one_line_error(code, err, str(seq), *needles, flag)
    assert "--max-gap" not in err
    code, out, err = run(capsys, *argv, flag)
    assert code == 0, err
    assert f"repair: {seq}: " in err and "average mean AOE" in out
    # the same from Python: the keyword load_sequence takes, and the repair recorded
    option = flag[2:].replace("-", "_")
    with pytest.raises(DataError, match=f"pass {option}=True") as e:
        learning.load_sequence(seq)
    assert str(e.value).startswith(f"{seq}: ")
    assert learning.load_sequence(seq, **{option: True}).repairs


def test_ground_truth_covering_fewer_samples_than_the_tracker_levels_on(capsys, tmp_path):
    """The shipped model (bias tracking) on a recording whose ground truth covers 8 IMU
    samples: one line naming the sequence and the 10 the tracker needs, before any work."""
    seq = write_sequence(tmp_path / "short", seconds=5.0)
    gt = seq / "groundtruth.csv"
    gt.write_text("\n".join(gt.read_text().splitlines()[:9]) + "\n")
    code, _, err = run(capsys, "learn", "evaluate", "euroc", str(seq))
    one_line_error(code, err, "'short'", "8 IMU samples", "at least 10")


def test_the_python_api_names_bad_arguments(folders):
    seq = learning.load_sequence(folders["seq"])
    model = learning.load(folders["model"])
    with pytest.raises(ValueError, match=r"Sequence.gyro must have shape \(2400, 3\)"):
        learning.Sequence("x", seq.t, seq.gyro[:-1], seq.accel, seq.q, seq.p, seq.v)
    with pytest.raises(ValueError, match="Sequence.q must hold unit quaternions"):
        learning.Sequence("x", seq.t, seq.gyro, seq.accel, 2 * seq.q, seq.p, seq.v)
    with pytest.raises(ValueError, match="NaN or inf at rows"):
        learning.Sequence("x", seq.t, seq.gyro * np.nan, seq.accel, seq.q, seq.p, seq.v)
    with pytest.raises(ValueError, match="model must be a jaximu.learning.Denoiser"):
        learning.evaluate_sequence("euroc", seq)
    with pytest.raises(ValueError, match="seq must be a jaximu.learning.Sequence"):
        learning.evaluate_sequence(model, str(folders["seq"]))
    with pytest.raises(learning.data.DataError, match="non-empty list"):
        learning.train([])
    with pytest.raises(ValueError, match=r"sequences\[1\] must be"):
        learning.train([seq, "x"])
    with pytest.raises(ValueError, match="unknown pretrained model"):
        learning.pretrained("kitti")
    with pytest.raises(ValueError, match=r"path must be a model folder .* got NoneType None"):
        learning.load(None)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(steps=0), r"TrainConfig.steps must be a positive integer, got 0"),
        (dict(horizons=(16.5, 33)), r"TrainConfig.horizons\[0\] must be a positive integer"),
        (dict(horizons=(0,)), r"TrainConfig.horizons\[0\] must be a positive integer"),
        (dict(horizons=(16, 48)), r"TrainConfig.horizons must each be twice"),
        (dict(learning_rate=-1e-3), r"TrainConfig.learning_rate must be positive"),
        (dict(train_seconds=float("nan")), r"TrainConfig.train_seconds must be positive"),
        (dict(gyro_noise=-1.0), r"TrainConfig.gyro_noise must be non-negative"),
        (dict(ema=1.0), r"TrainConfig.ema must be in \[0, 1\)"),
        (dict(recording_offsets="no"), r"TrainConfig.recording_offsets must be True or False"),
    ],
)
def test_train_settings_outside_their_domain_are_refused_by_name(kwargs, message):
    with pytest.raises(ValueError, match=message):
        learning.TrainConfig(**kwargs)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(rate_hz=-200.0), r"ModelConfig.rate_hz must be positive"),
        (dict(channels=(4, 0), dilations=(1, 2)), r"ModelConfig.channels\[1\] must be a pos"),
        (dict(dropout=1.5), r"ModelConfig.dropout must be in \[0, 1\)"),
        (dict(gyro_density=0.0), r"ModelConfig.gyro_density must be positive"),
        (dict(input_std=(1.0,) * 5), r"ModelConfig.input_std must have shape \(6,\), got \(5,\)"),
        (dict(gyro_bias=(0.0, np.nan, 0.0)), r"ModelConfig.gyro_bias contains non-finite values"),
        (dict(kernel=4), r"ModelConfig.kernel must be a positive odd number"),
        (dict(input_std=5.0), r"ModelConfig.input_std must be a sequence of numbers"),
        (dict(accel_network=True), r"ModelConfig.accel_network = True .* pass accel_head=True"),
    ],
)
def test_model_settings_outside_their_domain_are_refused_by_name(kwargs, message):
    with pytest.raises(ValueError, match=message):
        ModelConfig(**kwargs)


def test_the_model_takes_samples_of_one_shape_and_computes_integers_in_float32(folders):
    model = learning.load(folders["model"])
    rng = np.random.default_rng(0)
    g = rng.integers(-2, 3, (50, 3))
    a = rng.integers(8, 11, (50, 3))
    c = model(g, a)
    # integers are samples in rad/s and m/s², computed in float32 (as the engine does),
    # never truncated: the corrected rate is the float one's
    assert c.gyro.dtype == np.float32
    ref = model(g.astype(np.float32), a.astype(np.float32))
    np.testing.assert_array_equal(np.asarray(c.gyro), np.asarray(ref.gyro))
    with pytest.raises(ValueError, match=r"gyro must have shape \(\.\.\., T, 3\)"):
        model(g[:, :2], a)
    with pytest.raises(ValueError, match="gyro and accel must have one shape"):
        model(g, a[:-1])
    with pytest.raises(ValueError, match="accel must be an array of numbers"):
        model(g, "a")
    seq = learning.load_sequence(folders["seq"])
    with pytest.raises(ValueError, match="dtype must be a floating dtype"):
        learning.evaluate_sequence(model, seq, dtype=np.int32)
    with pytest.raises(ValueError, match="train_seconds must be positive"):
        learning.data.split(seq, 0.0)


def test_training_and_uncertainty_arguments_are_checked_before_any_work(folders):
    seq = learning.load_sequence(folders["seq"])
    model = learning.load(folders["model"])
    cfg = learning.TrainConfig(steps=1, train_seconds=6.0)
    with pytest.raises(ValueError, match="minutes must be positive"):
        learning.train([seq], cfg, TINY, minutes=-1.0)
    with pytest.raises(ValueError, match="seed must be an integer, got 1.5"):
        learning.train([seq], cfg, TINY, seed=1.5)
    with pytest.raises(ValueError, match="bias_sigma must be positive"):
        learning.uncertainty.with_bias_sigma(model, -1.0)
    with pytest.raises(ValueError, match="reference_sigma must be positive"):
        learning.uncertainty.with_reference_sigma(model, float("nan"))
    with pytest.raises(ValueError, match="gyro and accel hold no samples"):
        model(np.zeros((0, 3)), np.zeros((0, 3)))
    c = model(seq.gyro[:64], seq.accel[:64])
    q = seq.q[:65]
    with pytest.raises(ValueError, match="no window of 128 samples fits in 64 samples"):
        learning.losses.increment_loss(c, q, 0.005, (64, 128))
    with pytest.raises(ValueError, match="horizons must each be twice the one before"):
        learning.losses.increment_loss(c, q, 0.005, (16, 24))


def test_evaluate_notes_a_model_worse_than_the_raw_gyro(folders, capsys, tmp_path):
    """A model whose stored gyro bias is not the recording's (another kind of IMU) ends
    worse than the raw gyro: the command says so beside the table."""

    def evaluate_with_bias(name, gyro_bias):
        cfg = dataclasses.replace(TINY, gyro_bias=gyro_bias)
        path = learning.save(tmp_path / name, Denoiser(cfg, jax.random.key(0)), {"seed": 0})
        return run(capsys, "learn", "evaluate", str(path), str(folders["seq"]))

    code, out, err = evaluate_with_bias("other", (0.05, -0.05, 0.0))
    assert code == 0, err
    assert "worse than the raw gyro on seq" in out and "0.0500 -0.0500 0.0000" in out
    code, out, _ = evaluate_with_bias("same", (-0.002, 0.021, 0.077))  # write_sequence's bias
    assert code == 0 and "worse than the raw gyro" not in out


def test_leave_one_out_with_one_folder_is_refused_before_any_work(folders, capsys, tmp_path):
    out = tmp_path / "m"
    code, _, err = run(
        capsys, "learn", "train", str(folders["seq"]), "--out", str(out), "--leave-one-out"
    )
    one_line_error(code, err, "--leave-one-out needs two sequence folders", "leave the flag out")
    assert not out.exists()
    code, _, err = run(
        capsys, "learn", "train", str(folders["seq"]), "--out", str(out), "--leave-one-out-worst"
    )
    one_line_error(code, err, "--leave-one-out-worst needs two sequence folders", "leave the flag")
    assert not out.exists()
    two = [str(folders["seq"])] * 2
    code, _, err = run(
        capsys, "learn", "train", *two, "--out", str(out), "--leave-one-out", "--accel-network"
    )
    one_line_error(code, err, "--accel-network keeps the accelerometer's", "leave one of the two")
    assert not out.exists()


@pytest.mark.parametrize(
    "extra, needles",
    [
        (["--velocity-sigma", "0"], ("--velocity-sigma must be a positive number of m/s", "got 0")),
        (["--velocity-sigma", "nan"], ("--velocity-sigma must be a positive number", "got nan")),
        (["--learning-rate", "0"], ("--learning-rate must be a positive number below 1",)),
        (["--learning-rate", "inf"], ("--learning-rate must be", "got inf")),
        (["--validate-every", "0"], ("--validate-every must be a positive number", "got 0")),
        (
            ["--velocity-sigma", "3", "--no-bias-tracking"],
            ("--no-bias-tracking turns the tracker off", "leave one of the two"),
        ),
    ],
)
def test_bad_recipe_settings_are_refused_before_any_work(folders, capsys, tmp_path, extra, needles):
    out = tmp_path / "m"
    code, _, err = run(capsys, "learn", "train", str(folders["seq"]), "--out", str(out), *extra)
    one_line_error(code, err, *needles)
    assert not out.exists()
