"""Tests of the compile cache ([KC-1]..[KC-5]) on small programs (no simulator)."""

from __future__ import annotations

import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("jax")
pytest.importorskip("kinetix")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from jax.sharding import Mesh, NamedSharding, PartitionSpec  # noqa: E402

from softrtc.kinetix import cache  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]


def test_default_cache_dir_from_environment(monkeypatch, tmp_path):
    """KC-1: $SOFTRTC_JAX_CACHE names the folder, 'off' disables it, else the per-user XDG folder."""
    monkeypatch.setenv(cache.CACHE_ENV, str(tmp_path / "c"))
    assert cache.default_cache_dir() == tmp_path / "c"
    for off in ("off", "OFF", "0", "", "none"):
        monkeypatch.setenv(cache.CACHE_ENV, off)
        assert cache.default_cache_dir() is None
    monkeypatch.delenv(cache.CACHE_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache.default_cache_dir() == tmp_path / "xdg" / "softrtc" / "jax"
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert cache.default_cache_dir() == Path.home() / ".cache" / "softrtc" / "jax"


def test_enable_sets_jax_cache_with_lock_and_rejects_unwritable(tmp_path, restore_cache):
    """KC-1, KC-2: JAX's cache goes to DIR/xla/<host id> with a size bound (which turns on its file lock);
    an explicit folder that cannot be written is a ValueError naming path; None turns it off."""
    d = cache.enable_compile_cache(tmp_path / "cc")
    assert d == tmp_path / "cc" and (d / "xla" / cache.host_id()).is_dir() and (d / "programs").is_dir()
    assert jax.config.jax_compilation_cache_dir == str(d / "xla" / cache.host_id())
    assert jax.config.jax_compilation_cache_max_size == cache.MAX_CACHE_BYTES > 0
    assert jax.config.jax_persistent_cache_min_compile_time_secs == cache.MIN_COMPILE_S
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(ValueError, match="^path "):
        cache.enable_compile_cache(blocker / "sub")
    assert cache.enable_compile_cache(None) is None and cache.cache_dir() is None
    assert jax.config.jax_compilation_cache_dir is None


def test_default_folder_unwritable_turns_cache_off_with_warning(monkeypatch, tmp_path, restore_cache):
    """KC-1: an unwritable default folder never stops a run: the cache is off, with a warning."""
    blocker = tmp_path / "file"
    blocker.write_text("x")
    monkeypatch.setenv(cache.CACHE_ENV, str(blocker / "sub"))
    with pytest.warns(UserWarning, match="compile cache off"):
        assert cache.enable_compile_cache(True) is None


def _program(tmp_path):
    mesh = Mesh(np.array(jax.devices()), ("env",))
    rep, env = NamedSharding(mesh, PartitionSpec()), NamedSharding(mesh, PartitionSpec("env"))

    def fn(params, keys, d):
        x = jax.vmap(lambda k: jax.random.normal(k, (3,)))(keys)
        return {"x": x.sum(1) * params["w"] + d, "n": x.shape[0]}

    args = ({"w": jnp.float32(2.0)}, jax.random.split(jax.random.key(3), 4), jnp.arange(4, dtype=jnp.float32))
    return fn, args, (rep, env, env), rep


def test_program_cache_round_trip_and_damaged_entry(tmp_path, restore_cache):
    """KC-3, KC-4: a program is compiled once, then comes from memory, then (memory cleared, as a new
    process) from disk, each giving the outputs of a plain jax.jit of the function; a damaged file warns,
    recompiles and is replaced; a different config is a different program."""
    cache.enable_compile_cache(tmp_path / "cc")
    fn, args, shard, out = _program(tmp_path)
    want = jax.jit(fn)(*args)  # the same XLA program, compiled without the cache
    p1 = cache.compile_program("t", fn, args, shard, out, config=("a",))
    assert p1.source == "compiled"
    np.testing.assert_array_equal(np.asarray(p1(*args)["x"]), np.asarray(want["x"]))
    assert cache.compile_program("t", fn, args, shard, out, config=("a",)).source == "memory"
    cache.clear_memory()
    p2 = cache.compile_program("t", fn, args, shard, out, config=("a",))
    assert p2.source == "disk"
    np.testing.assert_array_equal(np.asarray(p2(*args)["x"]), np.asarray(want["x"]))
    files = list((tmp_path / "cc" / "programs").glob("t-*.bin"))
    assert len(files) == 1
    files[0].write_bytes(b"not a program")
    cache.clear_memory()
    with pytest.warns(UserWarning, match="unreadable"):
        p3 = cache.compile_program("t", fn, args, shard, out, config=("a",))
    assert p3.source == "compiled" and files[0].stat().st_size > 100
    assert cache.compile_program("t", fn, args, shard, out, config=("b",)).source == "compiled"
    assert len(list((tmp_path / "cc" / "programs").glob("t-*.bin"))) == 2
    with pytest.raises(ValueError, match="^args must have the structure"):
        p1(args[0], args[1])


def test_program_stored_after_a_layer1_hit_runs_from_disk(tmp_path, restore_cache):
    """KC-2, KC-3: a program compiled again after its layer-2 file was removed (layer 1 warm from the
    first compile, with no size threshold) is stored whole: loaded from disk it runs and gives the
    outputs of a plain jax.jit. (An executable JAX reloads from layer 1 serialises without some of its
    kernels; storing it gives a file that fails with "Function ... not found".)"""
    cache.enable_compile_cache(tmp_path / "cc")
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)  # store even this small program
    fn, args, shard, out = _program(tmp_path)

    def scanned(params, keys, d):  # loops and fusions, as a rollout has
        def body(c, _):
            c = jnp.where(c > 0, jnp.sin(c) * params["w"] + c, jnp.cos(c) - d)
            return c, c.sum()
        return jax.lax.scan(body, fn(params, keys, d)["x"], None, length=7)

    want = jax.jit(scanned)(*args)
    # Without the bypass of [KC-3] this first compile also fills layer 1, and the second one reloads it.
    assert cache.compile_program("s", scanned, args, shard, out).source == "compiled"
    for f in (tmp_path / "cc" / "programs").glob("s-*.bin"):
        f.unlink()
    cache.clear_memory()
    assert cache.compile_program("s", scanned, args, shard, out).source == "compiled"
    cache.clear_memory()
    p = cache.compile_program("s", scanned, args, shard, out)
    assert p.source == "disk"
    got = p(*args)
    np.testing.assert_allclose(np.asarray(got[0]), np.asarray(want[0]), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(got[1]), np.asarray(want[1]), rtol=1e-6)


def test_program_key_changes_with_every_input(restore_cache, monkeypatch):
    """KC-3, KC-2: the key covers name, config, argument shapes, dtypes and shardings, the host CPU and the
    source digest; the host id changes with the CPU's feature flags and model."""
    mesh = Mesh(np.array(jax.devices()), ("env",))
    rep = NamedSharding(mesh, PartitionSpec())
    a = [jax.ShapeDtypeStruct((4,), jnp.float32, sharding=rep)]
    tree = jax.tree.structure((1,))
    base = cache.program_key("n", ("c",), a, [rep], tree, rep)
    assert base == cache.program_key("n", ("c",), a, [rep], tree, rep)
    others = [cache.program_key("m", ("c",), a, [rep], tree, rep),
              cache.program_key("n", ("d",), a, [rep], tree, rep),
              cache.program_key("n", ("c",), [jax.ShapeDtypeStruct((5,), jnp.float32, sharding=rep)], [rep], tree,
                                rep),
              cache.program_key("n", ("c",), [jax.ShapeDtypeStruct((4,), jnp.int32, sharding=rep)], [rep], tree,
                                rep)]
    host = cache.host_id()
    assert len(host) == 16 and host == cache.host_id()
    monkeypatch.setattr(cache, "cpu_features", lambda: ("avx2", "sse2"))
    host_avx2 = cache.host_id()
    others.append(cache.program_key("n", ("c",), a, [rep], tree, rep))
    monkeypatch.setattr(cache, "cpu_features", lambda: ("avx2", "avx512f", "sse2"))
    assert cache.host_id() != host_avx2
    others.append(cache.program_key("n", ("c",), a, [rep], tree, rep))
    monkeypatch.setattr(cache, "cpu_model", lambda: "another CPU")
    assert cache.host_id() not in (host_avx2, host)
    assert len({base, *others}) == 7
    fp = cache.source_fingerprint()
    assert len(fp) == 64 and fp == cache.source_fingerprint()


_WRITER = r"""
import sys, jax, jax.numpy as jnp, numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from softrtc.kinetix import cache
cache.enable_compile_cache(sys.argv[1])
rep = NamedSharding(Mesh(np.array(jax.devices()), ("env",)), PartitionSpec())
def fn(x):
    for i in range(60):
        x = jnp.sin(x) * 1.01 + i
    return x
p = cache.compile_program("shared", fn, (jnp.ones(3),), (rep,), rep, config=("s",))
print(p.source, float(p(jnp.ones(3))[0]))
"""


@pytest.mark.slow
def test_two_processes_share_one_cache_folder(tmp_path):
    """KC-2, KC-4: two processes compiling the same program into one folder at once both succeed with
    equal results, and a third process loads it from disk."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    cmd = [sys.executable, "-c", _WRITER, str(tmp_path / "cc")]
    procs = [subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env)
             for _ in range(2)]
    outs = [p.communicate(timeout=600)[0].split() for p in procs]
    assert all(p.returncode == 0 for p in procs)
    assert outs[0][1] == outs[1][1]
    third = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert third.returncode == 0
    assert third.stdout.split() == ["disk", outs[0][1]]


def test_bench_ratios_and_table_by_hand():
    """KC-6: warm/cold, rollout cold compile / bare env's, throughput / bare env's, the policy-alone bound
    bare / (bare + policy) and the harness ratio rollout / (bare + policy alone), overall and per round,
    from hand values; the table prints them with the targets; a family without the bare env is an error."""
    from softrtc.kinetix.compile_bench import add_policy_bounds, add_ratios, format_compile_bench

    progs = {"bare": {"cold_s": 20.0, "warm_s": 1.0, "run_s": 16.0, "warm_source": "disk"},
             "rtc": {"cold_s": 25.0, "warm_s": 2.0, "run_s": 20.0, "warm_source": "disk", "method": "naive"}}
    out = add_ratios(progs, 16384)
    assert out["bare"]["steps_per_s"] == 1024.0 and out["rtc"]["steps_per_s"] == 819.2
    assert out["bare"]["warm_over_cold"] == 0.05 and out["rtc"]["warm_over_cold"] == 0.08
    assert out["rtc"]["cold_over_bare"] == 1.25 and out["rtc"]["throughput_over_bare"] == 0.8
    text = format_compile_bench({"level": "grasp_easy", "num_envs": 64, "env_steps": 16384, "policy_params": 10,
                                 "num_devices": 1, "device": "cpu", "cpu": "x", "programs": out})
    assert "rollout rtc | 25.0 | 2.00 (disk) | 0.080 | 20.0 | 819 | compile 1.25x, throughput 0.800x" in text
    assert "warm/cold <= 0.10" in text
    # The policy-alone line: bare 16 s + chunks 4 s bound the throughput at 16 / 20 = 0.8.
    alone = add_policy_bounds({"rtc": {"calls": 64, "run_s": 4.0}}, 16.0)
    assert alone["rtc"]["bound_over_bare"] == 0.8
    with pytest.raises(ValueError, match="^policy_alone entries must have a positive float 'run_s'"):
        add_policy_bounds({"rtc": {"calls": 64, "run_s": 0.0}}, 16.0)
    text = format_compile_bench({"level": "grasp_easy", "num_envs": 64, "env_steps": 16384, "policy_params": 10,
                                 "num_devices": 1, "device": "cpu", "cpu": "x", "programs": out,
                                 "policy_alone": alone})
    assert ("policy alone, rtc: 64 chunk requests x 64 envs, no env step | run 4.0 s | bare env + policy alone "
            "bound the throughput at 0.800x") in text
    # [KC-6] the throughput target: rollout 20 s / (bare 16 s + policy alone 4 s) = 1.0; per round from the
    # rounds' own runs: 21 / (17 + 4) = 1.0 and 22 / (16 + 4) = 1.1.
    from softrtc.kinetix.compile_bench import HARNESS_TARGET, harness_ratios

    timed = {"bare": dict(out["bare"], run_times_s=[17.0, 16.0]), "rtc": dict(out["rtc"], run_times_s=[21.0, 22.0])}
    h = harness_ratios(timed, {"rtc": dict(alone["rtc"], run_times_s=[4.0, 4.0])})
    assert h["rtc"]["over_parts"] == 1.0 and h["rtc"]["by_round"] == [1.0, 1.1] and HARNESS_TARGET == 1.10
    text = format_compile_bench({"level": "grasp_easy", "num_envs": 64, "env_steps": 16384, "policy_params": 10,
                                 "num_devices": 1, "device": "cpu", "cpu": "x", "programs": timed,
                                 "policy_alone": {"rtc": dict(alone["rtc"], run_times_s=[4.0, 4.0])}})
    assert ("harness, rtc: rollout 20.0 s / (bare env 16.0 s + policy alone 4.0 s) = 1.000x (per round 1.000 to "
            "1.100, median 1.050)") in text
    assert "rollout run time <= 1.10x (bare env + policy alone) in the same rounds" in text
    with pytest.raises(ValueError, match="^programs must hold the rollout of every policy_alone family"):
        harness_ratios({"bare": out["bare"]}, alone)
    with pytest.raises(ValueError, match="^programs must hold 'bare'"):
        add_ratios({"rtc": progs["rtc"]}, 10)
    with pytest.raises(ValueError, match="^programs entries must have a positive float 'run_s'"):
        add_ratios({"bare": dict(progs["bare"], run_s=0.0), "rtc": progs["rtc"]}, 10)
