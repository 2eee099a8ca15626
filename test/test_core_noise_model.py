"""Noise model: Eq. 5/6, interpolation, empty cells, file round trip and bad files."""

import logging

import numpy as np
import pytest

from egovib_ros.core import NoiseModel, analysis_window
from egovib_ros.core.noise_model import SCHEMA_VERSION
from egovib_ros.errors import ModelFileError

GRID = (np.array([-1.0, 0.0, 1.0]), np.array([-0.5, 0.0, 0.5]))


def tiny_model(measured="superposition", mean=None, std=None, counts=None):
    """3 x 3 grid, one channel, L = 4 (3 bins): small enough to check by hand."""
    shape = (3, 3, 1, 3)
    return NoiseModel(
        grid=GRID,
        joint_names=("a", "b"),
        channels=("combined",),
        mean=np.zeros(shape) if mean is None else mean,
        std=np.zeros(shape) if std is None else std,
        counts=np.ones((3, 3), dtype=int) if counts is None else counts,
        block_length=4,
        hop=2,
        window=analysis_window(4, 2),
        measured=measured,
    )


def test_eq6_superposition_matches_hand_computation():
    mean = np.zeros((3, 3, 1, 3))
    std = np.zeros((3, 3, 1, 3))
    mean[1, 1, 0] = [0.5, 0.5, 0.5]
    std[1, 1, 0] = [1.2, 0.0, 0.0]  # background (0, 0)
    mean[0, 1, 0] = [2.0, 3.0, 4.0]
    std[0, 1, 0] = [0.3, 0.3, 0.0]  # joint a = -1 alone
    mean[1, 2, 0] = [1.0, 1.0, 1.0]
    std[1, 2, 0] = [0.4, 0.4, 2.0]  # joint b = +0.5 alone
    model = tiny_model(mean=mean, std=std)
    # The estimate table (Eq. 5) is mean + std: mu = 2 + 1 - 0.5 etc.,
    # sd = sqrt(0.3^2 + 0.4^2 + 1.2^2) = sqrt(1.69) = 1.3
    np.testing.assert_allclose(model.estimate_table()[0, 2, 0], [3.8, 4.0, 6.5])
    # Cells on an axis reproduce their own mean (the background cancels).
    np.testing.assert_allclose(model.estimate_table(include_std=False)[0, 1, 0], mean[0, 1, 0])


def test_estimate_interpolates_bilinearly_and_clamps_outside_grid():
    rng = np.random.default_rng(0)
    mean = rng.uniform(1, 2, size=(3, 3, 1, 3))
    model = tiny_model(measured="full", mean=mean)
    at_cell, outside = model.estimate(np.array([[1.0, -0.5]]))
    np.testing.assert_allclose(at_cell[0], mean[2, 0])
    assert not outside[0]
    middle, _ = model.estimate(np.array([[0.5, -0.25]]))
    np.testing.assert_allclose(middle[0], mean[1:3, 0:2].mean(axis=(0, 1)))
    beyond, outside = model.estimate(np.array([[7.0, -0.5], [0.5, -0.25]]))
    np.testing.assert_allclose(beyond[0], mean[2, 0])
    assert outside.tolist() == [True, False]
    # The one-block path (streaming) gives the same bits as the vectorised one.
    one, _ = model.estimate(np.array([[0.37, 0.11]]))
    many, _ = model.estimate(np.array([[0.37, 0.11], [0.0, 0.0]]))
    np.testing.assert_array_equal(one[0], many[0])


def test_empty_cells_are_filled_by_superposition_and_logged(caplog):
    rng = np.random.default_rng(1)
    mean = rng.uniform(1, 2, size=(3, 3, 1, 3))
    counts = np.ones((3, 3), dtype=int)
    counts[0, 0] = 0  # off-axis cell never visited
    model = tiny_model(measured="full", mean=mean, counts=counts)
    with caplog.at_level(logging.INFO, logger="egovib_ros.core"):
        table = model.estimate_table()
    # the one unmeasured cell by Eq. 6 (std 0), every other one its measurement
    expected = mean.copy()
    expected[0, 0] = mean[0, 1] + mean[1, 0] - mean[1, 1]
    np.testing.assert_allclose(table, expected)
    # said once, at info level: the calibration's coverage lines and `model show` say it too
    assert "1 of 9 cells are not measured" in caplog.text
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]


def test_save_load_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(2)
    model = tiny_model(
        measured="full",
        mean=rng.uniform(size=(3, 3, 1, 3)),
        std=rng.uniform(size=(3, 3, 1, 3)),
        counts=rng.integers(0, 100, size=(3, 3)),
    )
    model.provenance["source"] = "bags/sweep"
    path = tmp_path / "model.npz"
    model.save(path)
    loaded = NoiseModel.load(path)
    fields = (
        "grid",
        "joint_names",
        "cells",
        "cell_mean",
        "cell_std",
        "cell_counts",
        "sample_rate_hz",
        "block_length",
        "hop",
        "window",
        "window_name",
        "band_hz",
        "band_order",
        "channels",
        "measured",
        "profile",
        "provenance",
        "mean",
        "std",
        "counts",
    )
    for name in fields:
        a, b = getattr(model, name), getattr(loaded, name)
        if name == "provenance":
            assert b["source"] == "bags/sweep" and b["software_version"] and b["created"]
        elif name == "grid":
            for ga, gb in zip(a, b):
                np.testing.assert_array_equal(ga, gb)
        elif isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b)
            assert a.dtype == b.dtype
        else:
            assert a == b, name
    with np.load(path, allow_pickle=False) as data:  # plain arrays only
        assert int(data["schema_version"]) == SCHEMA_VERSION


def test_bad_model_files_give_one_line_errors(tmp_path):
    model = tiny_model()
    good = tmp_path / "good.npz"
    model.save(good)
    with pytest.raises(ModelFileError, match="no such noise-model file"):
        NoiseModel.load(tmp_path / "absent.npz")
    with pytest.raises(ModelFileError, match="a directory, not a noise-model file"):
        NoiseModel.load(tmp_path)  # a bag or output directory given as --model
    corrupt = tmp_path / "corrupt.npz"
    corrupt.write_bytes(good.read_bytes()[:200])
    with pytest.raises(ModelFileError, match="corrupt.npz: not a readable noise-model"):
        NoiseModel.load(corrupt)
    with np.load(good, allow_pickle=False) as data:
        fields = {k: data[k] for k in data.files}
    future = tmp_path / "future.npz"
    np.savez(future, **{**fields, "schema_version": np.array(SCHEMA_VERSION + 1)})
    with pytest.raises(ModelFileError, match="newer than this software supports") as info:
        NoiseModel.load(future)
    assert "\n" not in str(info.value) and "future.npz" in str(info.value)
    missing = tmp_path / "missing.npz"
    np.savez(missing, **{k: v for k, v in fields.items() if k != "std"})
    with pytest.raises(ModelFileError, match=r"missing field\(s\) \['std'\]"):
        NoiseModel.load(missing)
    other = tmp_path / "other.npz"
    np.savez(other, x=np.zeros(3))
    with pytest.raises(ModelFileError, match="not an egovib noise model"):
        NoiseModel.load(other)
    negative = tmp_path / "negative.npz"
    np.savez(negative, **{**fields, "mean": -np.ones_like(fields["mean"])})
    with pytest.raises(ModelFileError, match="negative or non-finite"):
        NoiseModel.load(negative)


def test_superposition_for_one_and_three_joints():
    rng = np.random.default_rng(3)
    one = NoiseModel(
        grid=(np.array([-1.0, 0.0, 1.0]),),
        joint_names=("a",),
        channels=("combined",),
        mean=rng.uniform(1, 2, (3, 1, 3)),
        std=rng.uniform(0, 1, (3, 1, 3)),
        counts=np.ones(3, dtype=int),
        block_length=4,
        hop=2,
        window=analysis_window(4, 2),
        measured="superposition",
    )
    # one joint: Eq. 6 is the identity
    np.testing.assert_allclose(one.estimate_table(include_std=False), one.mean)
    np.testing.assert_allclose(one.estimate_table(), one.mean + one.std)
    grid = tuple(np.array([-1.0, 0.0, 1.0]) for _ in range(3))
    mean, std = np.zeros((3, 3, 3, 1, 3)), np.zeros((3, 3, 3, 1, 3))
    mean[1, 1, 1], std[1, 1, 1] = 1.0, 0.2
    mean[2, 1, 1], mean[1, 2, 1], mean[1, 1, 2] = 3.0, 4.0, 5.0
    std[2, 1, 1], std[1, 2, 1], std[1, 1, 2] = 0.3, 0.4, 0.5
    three = NoiseModel(
        grid=grid,
        joint_names=("a", "b", "c"),
        channels=("combined",),
        mean=mean,
        std=std,
        counts=np.ones((3, 3, 3), dtype=int),
        block_length=4,
        hop=2,
        window=analysis_window(4, 2),
        measured="superposition",
    )
    mu = three.estimate_table(include_std=False)[2, 2, 2]
    np.testing.assert_allclose(mu[0], 3 + 4 + 5 - 2 * 1.0)
    table = three.estimate_table()
    np.testing.assert_allclose(table[2, 2, 2, 0] - mu[0], np.sqrt(0.09 + 0.16 + 0.25 + 2 * 0.04))
    value, _ = three.estimate(np.array([[1.0, 1.0, 1.0]]))
    np.testing.assert_allclose(value[0], table[2, 2, 2])


def test_malformed_fields_and_empty_models_are_one_line_errors(tmp_path):
    good = tmp_path / "good.npz"
    tiny_model().save(good)
    with np.load(good, allow_pickle=False) as data:
        fields = {k: data[k] for k in data.files}
    cases = {
        "n_joints": np.array([2, 2]),
        "joint_names": np.array("a"),
        "band_hz": np.array([150.0]),
        "sample_rate_hz": np.array("fast"),
        "grid_0": np.array([-1.0, np.nan, 1.0]),
        "hop": np.array(0),
    }
    for key, bad in cases.items():
        path = tmp_path / f"bad_{key}.npz"
        np.savez(path, **{**fields, key: bad})
        with pytest.raises(ModelFileError) as info:
            NoiseModel.load(path)
        assert str(info.value).startswith(str(path)) and "\n" not in str(info.value), key
    empty = tiny_model(measured="full", counts=np.zeros((3, 3), dtype=int))
    with pytest.raises(ModelFileError, match="no measured cell"):
        empty.estimate_table()
