"""Tests of the runtime benchmark (spec/32-runtime-bench.md, chapter B); never assert on timings."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

jax = pytest.importorskip("jax")
nnx = pytest.importorskip("flax.nnx")
import jax.numpy as jnp  # noqa: E402

from softrtc.jax import bench, bench_report, bench_vjp, fast_chunks  # noqa: E402
from softrtc.jax import cli as jax_cli  # noqa: E402

TINY = dict(arch="tiny", calls=3, warmup=1, batch_sizes=(1, 4), train_calls=2, train_batch=2, num_steps=2)


@pytest.fixture(scope="module")
def result():
    return bench.run_benchmark(bench.BenchConfig(**TINY))


def test_rows_and_json_structure(result, tmp_path):
    """B-1, B-10, B-14: every method row plus the straightforward naive and train-soft rows and the public-style
    guided soft row, per batch size."""
    keys = [r["key"] for r in result["rows"]]
    assert keys == list(bench.CHUNK_ROWS) + ["naive/straightforward", "train_soft_lam2/straightforward",
                                             "inference_soft/public"]
    assert [r["path"] for r in result["rows"]][-3:] == ["straightforward", "straightforward", "public"]
    assert sorted(result["chunk"]) == ["1", "4"]
    for per_b in result["chunk"].values():
        assert list(per_b) == keys
        for st in per_b.values():
            assert st["calls"] == TINY["calls"]
            assert st["p10_ms"] <= st["median_ms"] <= st["p90_ms"]
    for key in ("config", "architecture", "environment", "agreement", "tolerance", "compilations",
                "table_build_ms", "vjp_cost", "restricted_pullback", "train_step", "targets", "seconds"):
        assert key in result
    path = tmp_path / "sub" / "bench.json"
    bench_report.write_json(result, path)
    assert json.loads(path.read_text())["rows"] == result["rows"]


def test_environment_names_the_cpu_model(result, monkeypatch):
    """B-10: the result records the CPU model beside the core count and the table's header prints both; a
    result written without the model (an older file) still formats."""
    env = result["environment"]
    assert isinstance(env["cpu_model"], str) and env["cpu_model"] and env["cpu_count"] >= 1
    header = bench_report.format_table(result).splitlines()[0]
    assert f"({env['cpu_count']} cores, {env['cpu_model']})" in header
    older = dict(result, environment={k: v for k, v in env.items() if k != "cpu_model"})
    assert f"({env['cpu_count']} cores)" in bench_report.format_table(older).splitlines()[0]
    # Without /proc/cpuinfo the model comes from platform.processor(), else "unknown".
    import builtins
    real_open = builtins.open

    def no_cpuinfo(path, *a, **k):
        if str(path) == "/proc/cpuinfo":
            raise OSError("no such file")
        return real_open(path, *a, **k)

    from softrtc import _machine

    monkeypatch.setattr(builtins, "open", no_cpuinfo)
    monkeypatch.setattr(_machine.platform, "processor", lambda: "")
    assert bench_report.cpu_model() == "unknown"
    monkeypatch.setattr(_machine.platform, "processor", lambda: "arm64")
    assert bench_report.cpu_model() == "arm64"


def test_ratios_are_against_naive_of_the_same_run(result):
    """B-6: ratio = median of the row / median of the naive row of the same batch size."""
    for per_b in result["chunk"].values():
        naive = per_b["naive"]["median_ms"]
        assert per_b["naive"]["ratio"] == pytest.approx(1.0)
        for st in per_b.values():
            assert st["ratio"] == pytest.approx(st["median_ms"] / naive, rel=1e-9)
    ts = result["train_step"]
    assert ts["soft_over_hard"] == pytest.approx(ts["soft"]["median_ms"] / ts["hard"]["median_ms"])
    assert ts["soft_over_none"] == pytest.approx(ts["soft"]["median_ms"] / ts["none"]["median_ms"])


def test_fast_and_straightforward_agree(result):
    """B-3, B-4, B-5, B-14: the fast path and the public-style guided row give the straightforward chunks within
    float32 tolerance."""
    for per_b in result["agreement"].values():
        assert sorted(per_b) == sorted([*bench.CHUNK_ROWS, "inference_soft/public"])
        for a in per_b.values():
            assert a["ok"] and a["max_abs_diff"] <= 1e-4
    assert [t for t in result["targets"] if t["id"] == "B-5"][0]["pass"]


def test_one_compilation_per_batch_size(result):
    """B-7: the delay is traced, so rotating d over 0..4 compiles each row once per batch size."""
    assert result["config"]["delay"] is None
    for i, per_b in enumerate(result["compilations"].values(), start=1):
        assert set(per_b.values()) == {i}  # jit caches accumulate over the batch sizes


def test_targets_and_table(result):
    """B-8, B-9, B-10, B-14: every target is reported with PASS/FAIL and printed; the guided target is the slower
    fast guided row over the public-style guided row, at most 0.9x at every batch size."""
    names = [t["target"] for t in result["targets"]]
    for B in (1, 4):
        assert f"train-time samplers / naive, batch {B}" in names
        assert f"naive / straightforward naive, batch {B}" in names
        assert f"guided samplers / public-style guided, batch {B}" in names
    assert "soft / hard training step" in names and not any("guided samplers / naive" in n for n in names)
    by_name = {t["target"]: t for t in result["targets"]}
    for B in ("1", "4"):
        t, ch = by_name[f"guided samplers / public-style guided, batch {B}"], result["chunk"][B]
        slower = max(ch["inference_hard"]["median_ms"], ch["inference_soft"]["median_ms"])
        assert t["limit"] == 0.9 and t["value"] == pytest.approx(slower / ch["inference_soft/public"]["median_ms"])
        assert t["pass"] == (t["value"] <= 0.9)
    table = bench_report.format_table(result)
    assert "public-style" in table
    assert table.count("PASS") + table.count("FAIL") == len(result["targets"])
    assert "max|fast-sf|" in table and "training step" in table


def test_vjp_cost_context(result):
    """B-11: forward and forward + VJP are timed per batch size and printed as context, not as targets."""
    assert sorted(result["vjp_cost"]) == ["1", "4"]
    for vc in result["vjp_cost"].values():
        assert vc["forward_ms"] > 0 and vc["forward_vjp_ms"] > 0
        assert vc["ratio"] == pytest.approx(vc["forward_vjp_ms"] / vc["forward_ms"])
    table = bench_report.format_table(result)
    assert "context (not targets)" in table
    assert table.count("one forward + VJP / one forward") == 2
    assert table.count("guided / straightforward naive") == 2
    assert not any("VJP" in t["target"] for t in result["targets"])


def test_guided_rows_restrict_the_pull_back_with_enough_rows(result):
    """B-3, G-7: the guided rows take the restricted pull-back iff batch * min(H - s, s) >= 16."""
    g = fast_chunks.guided_tokens_for
    assert fast_chunks.RESTRICT_MIN_ROWS == 16
    assert g("inference_soft", 8, 4, 1) is None and g("inference_hard", 8, 4, 3) is None
    assert g("inference_soft", 8, 4, 4) == 4 and g("inference_hard", 8, 4, 32) == 4
    assert g("inference_soft", 8, 6, 8) == 2 and g("inference_soft", 8, 6, 7) is None  # min(H - s, s) = 2
    assert g("inference_soft", 8, 8, 32) is None and g("inference_soft", 1, 1, 32) is None  # s = H
    for method in ("naive", "train_hard", "train_soft"):
        assert g(method, 8, 4, 32) is None
    for args, word in [(("inference", 8, 4, 1), "method"), (("naive", 8, 9, 1), "s"), (("naive", 8, 4, 0), "batch"),
                       (("naive", 0, 1, 1), "H"), (("naive", 8, 4, 2.0), "batch")]:
        with pytest.raises(ValueError, match=word):
            g(*args)
    # The tiny benchmark (H 8, s 4) runs batch 1 with the full pull-back and batch 4 with the restricted one,
    # and both agree with the straightforward path (test_fast_and_straightforward_agree).
    assert result["restricted_pullback"] == {"1": False, "4": True}
    table = bench_report.format_table(result)
    assert "pull-back over all tokens" in table
    assert "pull-back restricted to j < H - s" in table


def test_encode_obs_splits_the_input_projection():
    """B-3: x W_x + encode_obs(obs) equals in_proj of the concatenation within float32 tolerance."""
    cfg = bench.BenchConfig(arch="tiny")
    pol = bench.make_policy(cfg)
    rng = np.random.default_rng(0)
    obs = jnp.asarray(rng.standard_normal((3, pol.obs_dim)), jnp.float32)
    x = jnp.asarray(rng.standard_normal((3, 8, pol.action_dim)), jnp.float32)
    cond = pol.time_conditioning(jnp.full((3, 8), 0.4))
    a = pol.apply_conditioned(obs, x, cond)
    b = pol.apply_conditioned(obs, x, cond, obs_encoding=pol.encode_obs(obs))
    np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-4, atol=1e-4)
    with pytest.raises(ValueError, match="obs_encoding"):
        pol.apply_conditioned(obs, x, cond, obs_encoding=jnp.zeros((3, 16)))
    # P-12: an encoding of another observation is caught when the values are concrete.
    with pytest.raises(ValueError, match="obs_encoding must equal encode_obs"):
        pol.apply_conditioned(obs, x, cond, obs_encoding=pol.encode_obs(obs + 1.0))
    with pytest.raises(ValueError, match="obs"):
        pol.encode_obs(jnp.zeros((3, pol.obs_dim + 1)))


def test_config_validation():
    """N-7, B-2: invalid options raise ValueError naming the argument."""
    for kw, name in [(dict(calls=0), "calls"), (dict(batch_sizes=(1, 1)), "batch_sizes"),
                     (dict(batch_sizes=[1]), "batch_sizes"), (dict(delay=5), "delay"),
                     (dict(path="slow"), "path"), (dict(arch="huge"), "arch"), (dict(calls=2.0), "calls"),
                     (dict(execute_horizon=9), "execute_horizon")]:
        with pytest.raises(ValueError, match=name):
            bench.BenchConfig(**kw)
    assert bench.BenchConfig().delays == (0, 1, 2, 3, 4)
    assert bench.BenchConfig(delay=3).delays == (3,)
    with pytest.raises(ValueError, match="config"):
        bench.run_benchmark({"calls": 1})
    with pytest.raises(ValueError, match="res"):
        bench_report.format_table({})


def test_cli_options(capsys):
    """B-10: `softrtc bench runtime` parses its options; invalid ones exit with status 2."""
    import argparse

    parser = argparse.ArgumentParser()
    jax_cli.add_subparsers(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["bench", "runtime", "--batch-sizes", "1,4", "--delay", "2", "--calls", "7"])
    assert args.batch_sizes == (1, 4) and args.delay == 2 and args.calls == 7 and args.path == "fast"
    assert parser.parse_args(["bench", "runtime"]).out == "runs/bench_runtime.json"
    for bad_option in (["--batch-sizes", "0"], ["--batch-sizes", "1,,2"], ["--batch-sizes", "2,"],
                       ["--batch-sizes", "2,2"], ["--out", ""], ["--out", "softrtc"], ["--out", "README.md/x.json"]):
        with pytest.raises(SystemExit):
            parser.parse_args(["bench", "runtime", *bad_option])
    capsys.readouterr()
    bad = parser.parse_args(["bench", "runtime", "--delay", "7"])
    assert jax_cli.run_runtime(bad) == 2
    assert "--delay must be an integer in [0, 4]" in capsys.readouterr().err
    bad = parser.parse_args(["bench", "runtime", "--execute-horizon", "9"])
    assert jax_cli.run_runtime(bad) == 2
    assert "--execute-horizon must be an integer in [1, 8], got 9" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # ranges the parser knows are checked while parsing
        parser.parse_args(["bench", "runtime", "--steps", "0"])
    assert "--steps: value must be an integer in [1, 1000], got 0" in capsys.readouterr().err


def test_delay_rows_match_traced_delay_tables():
    """B-3, B-7, S-6: a host-picked per-delay row gives the chunk of the traced-delay table path."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from flax import nnx

    from softrtc.jax import methods as JM
    from softrtc.jax.policy import FlowPolicy, PolicyConfig

    pol = FlowPolicy(obs_dim=5, action_dim=2, config=PolicyConfig(channel_dim=16, channel_hidden_dim=32,
                     token_hidden_dim=8, num_layers=1, action_chunk_size=8), rngs=nnx.Rngs(0))
    # adaLN kernels start at zero, which would make every delay's conditioning the same: perturb them all.
    rng = np.random.default_rng(3)
    nnx.update(pol, jax.tree.map(lambda a: jnp.asarray(0.3 * rng.standard_normal(a.shape), a.dtype), nnx.state(pol)))
    key = jax.random.PRNGKey(1)
    obs, noise, prior = (jax.random.normal(k, s) for k, s in
                         zip(jax.random.split(key, 3), [(2, 5), (2, 8, 2), (2, 8, 2)]))
    for method in ("train_soft", "inference_soft", "naive"):
        tables = JM.method_tables(method, pol, 8, 4, 3)
        rows = JM.delay_rows(method, tables)
        assert len(rows) == 5
        f = jax.jit(lambda row: JM.generate_chunk_from_row(method, pol, obs, noise, prior, 3, row))
        chunks = []
        for d in range(5):
            a = f(rows[d])
            b = JM.generate_chunk_conditioned(method, pol, obs, noise, prior, 4, jnp.int32(d), 3, tables=tables)
            # Two compilations of the same function: float32 rounding only ([P-14]).
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-5, rtol=1e-5)
            chunks.append(np.asarray(a))
        # The rows differ by delay (naive ignores d): a row mix-up would show.
        assert (method == "naive") == all(np.array_equal(chunks[0], c) for c in chunks[1:])
        assert f._cache_size() == 1
    import pytest
    with pytest.raises(ValueError, match="row must be"):
        JM.generate_chunk_from_row("train_soft", pol, obs, noise, prior, 3, {"weights": 0})


def test_vjp_ablation_cli_end_to_end(tmp_path, capsys):
    """B-12, G-7, P-17, P-19, P-20: `softrtc bench vjp` compiles every variant of the guided row, checks its
    chunks against the shipped ones, times them against naive, prints the table and writes JSON."""
    import argparse

    parser = argparse.ArgumentParser()
    jax_cli.add_subparsers(parser.add_subparsers(dest="command"))
    assert parser.parse_args(["bench", "vjp"]).out == "runs/bench_vjp.json"
    out = tmp_path / "vjp.json"
    args = parser.parse_args(["bench", "vjp", "--arch", "tiny", "--batch-sizes", "1,4", "--calls", "2",
                              "--warmup", "1", "--steps", "2", "--out", str(out)])
    assert args.func(args) == 0
    printed = capsys.readouterr().out
    for label, *_ in bench_vjp.VJP_VARIANTS.values():
        assert printed.count(label) == 2  # one line per batch size
    res = json.loads(out.read_text())
    assert set(res["variants"]) == set(bench_vjp.VJP_VARIANTS)
    for b, rule in (("1", False), ("4", True)):  # batch * min(H - s, s) >= 16 from batch 4 on ([B-3])
        flags = res["restricted_pullback"][b]
        assert flags["shipped"] is rule and flags["other_pullback"] is (not rule) and not flags["plain_autodiff"]
        assert all(a["ok"] for a in res["agreement"][b].values())
        assert res["agreement"][b]["shipped"]["max_abs_diff"] == 0.0
        # The other variants compute differently (autodiff, transposes, token groups): not bitwise the same.
        assert res["agreement"][b]["plain_autodiff"]["max_abs_diff"] > 0.0
        ch = res["chunk"][b]
        assert ch["naive"]["ratio"] == 1.0 and ch["shipped"]["over_shipped"] == 1.0
        assert all(ch[k]["calls"] == 2 for k in ch)
    bad = parser.parse_args(["bench", "vjp", "--arch", "tiny", "--execute-horizon", "9"])
    assert jax_cli.run_vjp(bad) == 2
    assert "--execute-horizon" in capsys.readouterr().err
    with pytest.raises(ValueError, match="run_vjp_ablation"):
        bench_vjp.format_vjp_table({})


def test_agreement_check_reports_a_disagreement(monkeypatch):
    """B-5: the agreement check compares against the straightforward chunks it is given, so a
    straightforward path off by 1e-3 is reported as not ok with that difference."""
    config = bench.BenchConfig(**TINY)
    policy = bench.make_policy(config)
    honest = bench._straightforward_fn

    def off_by(graphdef, treedef, method, window, s, T, *step):
        fn = honest(graphdef, treedef, method, window, s, T, *step)
        return lambda *args: fn(*args) + 1e-3

    names = ("naive", "train_soft_lam2")
    good = bench.check_agreement(config, policy, 1, names)
    assert all(a["ok"] and a["max_abs_diff"] <= 1e-4 for a in good.values())
    monkeypatch.setattr(bench, "_straightforward_fn", off_by)
    bad = bench.check_agreement(config, policy, 1, names)
    for a in bad.values():
        assert not a["ok"] and a["max_abs_diff"] == pytest.approx(1e-3, rel=0.2)


def test_agreement_checks_the_timed_delays(monkeypatch):
    """B-5: the check runs at every delay the run times: 0 .. min(s, H - s) by default, only D
    under --delay D."""
    seen = []
    honest = bench._agreement

    def spy(rows, reference, state, inputs, delays):
        seen.append([int(d) for d in delays])
        return honest(rows, reference, state, inputs, delays)

    monkeypatch.setattr(bench, "_agreement", spy)
    config = bench.BenchConfig(**TINY)
    policy = bench.make_policy(config)
    bench.check_agreement(config, policy, 1, ("naive",))
    bench.check_agreement(bench.BenchConfig(**TINY, delay=2), policy, 1, ("naive",))
    assert seen == [[0, 1, 2, 3, 4], [2]]


def test_public_style_guided_row_runs_as_the_release_does(monkeypatch):
    """B-14, G-2: the public-style guided row is a scanned loop (the straightforward row is unrolled), computes the
    time conditioning inside every step (one sin-cos embedding in the loop body, not a precomputed table), and
    is traced with plain autodiff for every block of the pull-back; its chunks equal the straightforward ones."""
    from softrtc.jax import bench_config

    cfg = bench.BenchConfig(arch="tiny", calls=1, warmup=1, batch_sizes=(1,), train_calls=0, num_steps=3)
    policy = bench.make_policy(cfg)
    graphdef, treedef, leaves = bench._params(policy)
    obs, noise, prior = bench_config.inputs(cfg, policy, 2, 1)[0]
    switches = []
    real = bench.autodiff_vjps

    def spy(**kw):
        switches.append(kw)
        return real(**kw)

    monkeypatch.setattr(bench, "autodiff_vjps", spy)
    public = bench._public_guided_fn(graphdef, treedef, "inference_soft", 4, 3)
    plain = bench._straightforward_fn(graphdef, treedef, "inference_soft", None, 4, 3)
    d = jnp.int32(2)
    pub_txt = str(jax.make_jaxpr(public)(leaves, None, obs, noise, prior, d))
    sf_txt = str(jax.make_jaxpr(plain)(leaves, None, obs, noise, prior, d))
    assert switches == [{"layer_norm": True, "gelu": True}]
    assert "scan" in pub_txt and "scan" not in sf_txt
    # The time embedding's sin: once in the scanned body, once per unrolled step of the straightforward row.
    assert pub_txt.count(" sin ") == 1 and sf_txt.count(" sin ") == 3
    for dd in range(5):
        a = np.asarray(public(leaves, None, obs, noise, prior, jnp.int32(dd)))
        b = np.asarray(plain(leaves, None, obs, noise, prior, jnp.int32(dd)))
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-4)


def test_bench_table_command_and_ranges(tmp_path, capsys, result):
    """B-15, N-11: `softrtc bench table` prints the last file's table and the ranges over all files, by hand:
    two runs whose guided ratios are 0.8 and 0.85 print 0.80-0.85; a file that is no result is one error line."""
    import copy

    from softrtc.cli import main

    a, b = copy.deepcopy(result), copy.deepcopy(result)
    for res, ratio in ((a, 0.8), (b, 0.85)):
        for ch in res["chunk"].values():
            ch["inference_hard"]["median_ms"] = ch["inference_soft"]["median_ms"] = 2.0
            ch["inference_soft/public"]["median_ms"] = 2.0 / ratio
    pa, pb = tmp_path / "a.json", tmp_path / "b.json"
    bench_report.write_json(a, pa)
    bench_report.write_json(b, pb)
    assert main(["bench", "table", str(pa), str(pb)]) == 0
    out = capsys.readouterr().out
    assert out.startswith(bench_report.format_table(bench_report.read_result(pb)))
    line = [ln for ln in out.splitlines() if ln.startswith("| guided samplers / public-style guided |")][0]
    assert line == "| guided samplers / public-style guided | 0.80-0.85 | 0.80-0.85 | 0.90 |"
    one = bench_report.format_ranges([bench_report.read_result(pa)])
    assert "| guided samplers / public-style guided | 0.80 | 0.80 | 0.90 |" in one
    (tmp_path / "bad.json").write_text('{"chunk": {}}')
    assert main(["bench", "table", str(tmp_path / "bad.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith(f"softrtc bench table: error: {tmp_path / 'bad.json'} is not a result of softrtc bench "
                          "runtime")
    with pytest.raises(ValueError, match=r"^results\[1\] must have the batch sizes of results\[0\]"):
        bench_report.format_ranges([a, dict(b, chunk={"1": b["chunk"]["1"]})])


RESULTS = sorted((Path(__file__).resolve().parents[2] / "results" / "bench").glob("runtime-*.json"))
README_BEGIN = "<!-- softrtc bench table results/bench/runtime-*.json -->"
README_END = "<!-- end of softrtc bench table -->"


def readme_block(results) -> str:
    """What the benchmarks page's runtime section shows between its markers: `softrtc bench table`'s output ([B-15])."""
    return (f"{README_BEGIN}\n```\n{bench_report.format_table(results[-1])}\n```\n\n"
            f"{bench_report.format_ranges(results)}\n{README_END}")


def test_readme_runtime_tables_are_the_committed_results():
    """B-15, B-10, B-9: the table and ratio ranges of the benchmarks page (docs/reports/benchmarks.md) are what
    `softrtc bench table` makes of the result files committed under results/bench/; the committed runs check
    their chunks and have every row."""
    assert len(RESULTS) >= 2, RESULTS
    results = [bench_report.read_result(p) for p in RESULTS]
    for res in results:
        assert res["config"]["arch"] == "benchmark" and res["config"]["path"] == "fast"
        assert [t for t in res["targets"] if t["id"] == "B-5"][0]["pass"]
        assert [r["key"] for r in res["rows"]][-1] == "inference_soft/public"
    readme = (Path(__file__).resolve().parents[2] / "docs" / "reports" / "benchmarks.md").read_text()
    i, j = readme.find(README_BEGIN), readme.find(README_END)
    assert 0 <= i < j, "the benchmarks page lacks the markers of the benchmark tables"
    assert readme[i:j + len(README_END)] == readme_block(results)

