import json
import math

import pytest

from bench import store


@pytest.mark.integration
def test_bench_store_reports_ingest_queries_and_memory(capsys):
    assert store.main(["--n", "2000", "--queries", "200", "--log-level", "WARNING"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in ("n", "ingest_per_s", "window_query_ms_p50", "window_query_ms_p99", "rss_mb", "db_mb",
                "window_size_mean", "retained", "ingested"):
        assert isinstance(result[key], (int, float)) and math.isfinite(result[key]) and result[key] > 0, key
    assert result["n"] == 2000 and result["ingested"] == 2000 and result["acked"] == 2000
    assert 0 < result["retained"] <= result["ingested"]
    assert result["window_query_ms_p99"] >= result["window_query_ms_p50"]
    assert result["window_queries"] == 200 and result["window_query_errors"] == 0
    # c_bin 4 over (2*5+1) vertices x (2*1+1) speed bins
    assert 0 < result["window_size_mean"] <= result["window_size_max"] <= 132


@pytest.mark.integration
def test_bench_store_bounds_unacknowledged_experiences(capsys):
    """--max-in-flight makes the producer wait for the store (as --n 1000000 needs) and loses nothing."""
    assert store.main(["--n", "1500", "--queries", "20", "--warmup", "0", "--max-in-flight", "200",
                       "--log-level", "WARNING"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["acked"] == result["ingested"] == 1500 and result["resent"] == 0
    assert result["ingest_store_cpu_us"] > 0
