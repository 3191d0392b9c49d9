"""A small run of the paper benchmark: the files it writes and the rows of its tables."""

import gpomap.benchmark
from gpomap.benchmark import run_paper_benchmark


def test_quick_paper_benchmark_writes_tables_and_figures(tmp_path, monkeypatch):
    # MSK-GPOM's tiles in this process (a pool of every core is half the CPU time of the run) and
    # its hyperparameters learnt on a 300-cell sample instead of 800 (learning itself is
    # test_mapping's and test_tiles'): this test is about the benchmark's rows, tables and figures.
    real = gpomap.benchmark.make_model

    def light(method, kernel=None, seed=0, resolution=0.1, n_workers=None, **options):
        if method == "msk":
            n_workers, options = 1, {"hyper_sample": 300, **options}
        return real(method, kernel, seed, resolution, n_workers, **options)

    monkeypatch.setattr(gpomap.benchmark, "make_model", light)
    result = run_paper_benchmark(
        tmp_path, methods=("msk", "ogm"), kernels=("se",), belgioioso_path=tmp_path / "absent.log", quick=True
    )
    assert [(r["method"], r["kernel"]) for r in result["rows"]] == [("msk", "se"), ("ogm", "-")]
    # Measured: held-out AUC 0.992 (MSK-GPOM, 300-cell sample; 0.991 with 800) and 0.975 (OGM);
    # against the true room 0.727 and 0.806.
    assert all(0.5 < r["auc"] <= 1.0 and 0.5 < r["truth_auc"] <= 1.0 for r in result["rows"])
    assert all(r["n_inputs"] > 0 for r in result["rows"])
    assert result["rows"][0]["tiles"] > 1
    table = (tmp_path / "tables.md").read_text()
    assert "Table II" in table and "| MSK-GPOM | se |" in table and "| 19.33 | 0.9266 | 16.30 % |" in table
    assert "| OGM | - |" in table and "Table III" not in table and "AUC vs true room" in table
    for name in ["roc_synthetic.png", "map_synthetic_msk_se.png"]:
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_unknown_experiment_is_refused(tmp_path):
    import pytest

    with pytest.raises(ValueError, match="unknown experiment"):
        run_paper_benchmark(tmp_path, experiments=("synthetic", "castle"))
