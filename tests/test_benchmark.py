"""A small run of the paper benchmark: the files it writes and the rows of its tables."""

from gpomap.benchmark import run_paper_benchmark


def test_quick_paper_benchmark_writes_tables_and_figures(tmp_path):
    result = run_paper_benchmark(
        tmp_path, methods=("msk", "ogm"), kernels=("se",), belgioioso_path=tmp_path / "absent.log", quick=True
    )
    assert [(r["method"], r["kernel"]) for r in result["rows"]] == [("msk", "se"), ("ogm", "-")]
    assert all(0.5 < r["auc"] <= 1.0 and 0.5 < r["truth_auc"] <= 1.0 for r in result["rows"])
    assert all(r["n_inputs"] > 0 for r in result["rows"])
    table = (tmp_path / "tables.md").read_text()
    assert "Table II" in table and "| MSK-GPOM | se |" in table and "| 19.33 | 0.9266 | 16.30 % |" in table
    assert "| OGM | - |" in table and "Table III" not in table and "AUC vs true room" in table
    for name in ["roc_synthetic.png", "map_synthetic_msk_se.png"]:
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_unknown_experiment_is_refused(tmp_path):
    import pytest

    with pytest.raises(ValueError, match="unknown experiment"):
        run_paper_benchmark(tmp_path, experiments=("synthetic", "castle"))
