"""`egovib bench --quick` writes every figure (as ratios to real time) with the machine noted."""

import json

from egovib_research.tools import bench
from egovib_ros.cli import main


def test_bench_quick_writes_json_and_markdown(tmp_path):
    out = tmp_path / "bench.json"
    assert main(["bench", "--json", str(out), "--quick", "--quiet"]) == 0
    data = json.loads(out.read_text())
    machine = data["machine"]
    assert machine["cores"] >= 1 and machine["cpu_model"] and machine["numpy"]
    figures = {
        **data["batch"],
        **data["stream"],
        **data["calibration"],
        **data["simulation_and_bags"],
    }
    for key in (
        "batch_x_realtime",
        "stream_hop_median_us",
        "stream_hop_p99_us",
        "calibration_s",
        "simulation_x_realtime",
        "bag_write_x_realtime",
        "bag_read_x_realtime",
    ):
        assert figures[key] > 0, key
    assert figures["stream_hop_p99_us"] >= figures["stream_hop_median_us"]
    assert data["calibration"]["cells"] == 441
    bags = data["bags"]  # denoise end to end beside a copy of the same bag
    for key in (
        "denoise_x_realtime",
        "denoise_zstd_x_realtime",
        "file_copy_x_realtime",
        "bag_copy_x_realtime",
        "denoise_vs_file_copy",
        "denoise_vs_bag_copy",
        "denoise_default_x_realtime",  # what `egovib denoise` with no option runs
        "denoise_default_vs_file_copy",
        "imu_stream_zstd_size_ratio",
    ):
        assert bags[key] > 0, key
    assert bags["denoise_bag_x_realtime"] == bags["denoise_default_x_realtime"]
    assert bags["zstd_output_size_ratio"] > 2 and bags["imu_stream_zstd_size_ratio"] > 2
    assert bags["bag_signal_s"] > 2.5
    for key in (
        "read_scanner",
        "read_mcap_library",
        "read_rosbags",
        "write_package",
        "write_mcap_library",
        "write_rosbags",
    ):
        assert bags["mcap"][f"{key}_msgs_per_s"] > 0, key
    methods = data["methods"]  # paper, cancel, hybrid on a simulated PR2 run
    for method in bench.METHODS:
        for name in ("batch", "batch_per_axis", "stream"):
            assert methods[f"{method}_{name}_x_realtime"] > 0
            assert methods[f"{method}_{name}_x_realtime_cpu"] > 0
    for method in ("cancel", "hybrid"):
        assert methods[f"{method}_batch_cpu_over_paper"] > 0
    assert "Method `hybrid`" in (tmp_path / "bench.md").read_text()
    assert "a bag copy" in (tmp_path / "bench.md").read_text()
    assert set(data["targets"]) == set(bench.TARGETS)
    assert all(t["met"] in (True, False) for t in data["targets"].values())
    markdown = (tmp_path / "bench.md").read_text()
    assert "x real time" in markdown and machine["cpu_model"] in markdown


def test_bench_output_in_missing_directory_is_created(tmp_path):
    out = tmp_path / "new" / "dir" / "b.json"
    md = tmp_path / "elsewhere.md"
    assert main(["bench", "--json", str(out), "--markdown", str(md), "--quick", "--quiet"]) == 0
    assert out.is_file() and md.is_file()


def test_synthetic_model_has_the_real_shape():
    model = bench.synthetic_model()
    assert model.grid_shape == (21, 21)
    assert model.mean.shape[-1] == 33
