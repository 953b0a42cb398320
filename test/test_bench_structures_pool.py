"""bench.structures_pool: the exact binomial interval against scipy.stats, and the pooling of made-up seeds."""

import json

import numpy as np
import pytest
import scipy.stats

from bench.structures_mc import CLEAN_INDEX_OFFSET, score
from bench.structures_pool import clopper_pearson, format_table, load, main, pool


@pytest.mark.parametrize("k,n", [(0, 10), (1, 10), (5, 10), (10, 10), (4, 279), (275, 287), (1, 500)])
def test_clopper_pearson_matches_the_beta_quantiles_of_scipy_stats(k, n):
    lo, hi = clopper_pearson(k, n)
    ref_lo = 0.0 if k == 0 else scipy.stats.beta.ppf(0.025, k, n - k + 1)
    ref_hi = 1.0 if k == n else scipy.stats.beta.ppf(0.975, k + 1, n - k)
    assert lo == pytest.approx(ref_lo, rel=1e-10, abs=1e-15) and hi == pytest.approx(ref_hi, rel=1e-10)
    assert lo <= k / n <= hi


def test_clopper_pearson_covers_at_least_its_level():
    # Exact coverage over every outcome of a binomial(40, p): at least 95 % for any p.
    n = 40
    ks = np.arange(n + 1)
    bounds = np.array([clopper_pearson(k, n) for k in ks])
    for p in (0.01, 0.05, 0.2, 0.5, 0.9):
        covered = (bounds[:, 0] <= p) & (p <= bounds[:, 1])
        assert scipy.stats.binom.pmf(ks, n, p)[covered].sum() >= 0.95


def test_clopper_pearson_refuses_impossible_counts():
    with pytest.raises(ValueError, match="0 <= k <= n"):
        clopper_pearson(5, 4)


def _record(index, mismatches, located, integrating=(False, False)):
    return {"index": index, "shape": [2, 2, 0], "integrating_outputs": list(integrating),
            "mismatches": [{"output": i, "column": j, "role": "input", "kind": "gain", "size": 0.5, "plant": {},
                            "model": {}} for i, j in mismatches],
            "located": [list(x) for x in located], "ambiguous": [], "rows": sorted({x[0] for x in located}),
            "collinear_columns": [], "kinds": {}, "analyze_time_s": 0.1, "repair": []}


def _result(seed, records, **config):
    cfg = {"runs": sum(r["index"] < CLEAN_INDEX_OFFSET for r in records), "clean_integrating": 0, "seed": seed,
           "samples": 3000, "alpha": 0.01, "jobs": 2, "element_window": "model", "noise_candidate": False,
           "options": {"min_size": 2}, "wall_time_s": 1.0, "machine": {}}
    cfg.update(config)
    return {"config": cfg, "runs": records}


def _write(tmp_path, name, result):
    path = tmp_path / name
    path.write_text(json.dumps(result), encoding="utf-8")
    return path


def test_pooling_scores_every_seed_and_their_union(tmp_path):
    seed_a = [_record(0, [(0, 0)], [(0, 0)]), _record(1, [], [(1, 1)]),                    # a hit, a false alarm
              _record(CLEAN_INDEX_OFFSET, [], [(0, 1)], integrating=(True, False))]
    seed_b = [_record(0, [(1, 0)], [(1, 0), (1, 1)]), _record(1, [(0, 1)], []),            # hit + fp, a miss
              _record(CLEAN_INDEX_OFFSET, [], [], integrating=(True, False))]
    files = [_write(tmp_path, "a.json", _result(0, seed_a)), _write(tmp_path, "b.json", _result(7, seed_b))]
    out = pool(load(files))
    assert out["config"]["seeds"] == [0, 7]
    a, b = (s["summary"]["element"] for s in out["per_seed"])
    assert (a["tp"], a["fp"], a["fn"]) == (1, 1, 0) and (b["tp"], b["fp"], b["fn"]) == (1, 1, 1)
    main_runs = [r for r in seed_a + seed_b if r["index"] < CLEAN_INDEX_OFFSET]
    assert out["pooled"]["element"] == score(main_runs)["element"]
    assert (out["pooled_clean_integrating"]["located"], out["pooled_clean_integrating"]["runs"]) == (1, 2)
    assert out["intervals95"]["precision"] == pytest.approx(clopper_pearson(2, 4))
    assert [(f["seed"], f["index"], f["element"]) for f in out["false_positives"]] == [(0, 1, [1, 1]), (7, 0, [1, 1])]
    table = format_table(out)
    assert "pooled over seeds 0, 7" in table and "0/1 (1, 1) no" in table and "7/0 (1, 1) yes" in table


def test_pooling_refuses_different_analyses_and_repeated_seeds(tmp_path, capsys):
    rec = [_record(0, [], [])]
    a = _write(tmp_path, "a.json", _result(0, rec))
    other_alpha = _write(tmp_path, "b.json", _result(1, rec, alpha=0.05))
    with pytest.raises(ValueError, match="b.json: config 'alpha' is 0.05"):
        load([a, other_alpha])
    with pytest.raises(ValueError, match="seed 0 is given twice"):
        load([a, _write(tmp_path, "c.json", _result(0, rec))])
    bad = tmp_path / "bad.json"
    bad.write_text("[1, 2]", encoding="utf-8")
    assert main([str(a), str(bad), "--out", str(tmp_path / "o.json")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "bad.json: not a bench.structures_mc result" in err
