"""Tests of the levels shipped with kinetix-env ([K-20]..[K-22]): names, padding, keys, commands."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

pytest.importorskip("jax")
pytest.importorskip("kinetix")

from softrtc.kinetix import levels as klev  # noqa: E402


def _raw(name):
    st, stem = name.split("_", 1)
    return json.loads((klev.package_levels_dir() / st / f"{stem}.json").read_text())


def test_package_names_and_one_error_for_unknown_names():
    """K-20: one name <set>_<stem> per JSON file of kinetix/levels/{s,m,l}; those names and the 12 pass, with
    @own too; anything else (bare stems, other sets, paths, the benchmark's names with @own) is one
    ValueError naming the argument, the form and `softrtc kinetix levels`."""
    files = sorted(f"{p.parent.name}_{p.stem}" for st in "sml" for p in (klev.package_levels_dir() / st).glob("*.json"))
    names = klev.package_level_names()
    assert sorted(names) == files and len(names) == len(set(names)) > 60
    assert names[0].startswith("s_") and names[-1].startswith("l_")
    for ok in ("m_h5_angry_birds", "s_h4_thrust_aim@own", "l_grasp_easy", "grasp_easy"):
        assert klev.check_level_name(ok) == ok
    assert klev.is_package_level("l_grasp_easy") and not klev.is_package_level("grasp_easy")
    for bad in ("h5_angry_birds", "x_h5_angry_birds", "m_nope", "m_../s/h4_thrust_aim", "grasp_easy@own",
                "m_h5_angry_birds@OWN", "", 3, None):
        with pytest.raises(ValueError, match=r"^levels entry must be one of the benchmark's levels \(grasp_easy, "
                                             r".*<set>_<name>\[@own\] with set s, m or l .*"
                                             r"list the valid names with `softrtc kinetix levels`; got "):
            klev.check_level_name(bad, "levels entry")


def test_package_levels_need_no_levels_dir(tmp_path):
    """K-20, K-2: the levels directory is resolved only for the benchmark's names: package names alone
    need none (and a given one must still be a directory); mixed with a benchmark name it is required."""
    assert klev.resolve_levels_dir(None, ("m_h5_angry_birds",)) == klev.package_levels_dir()
    assert klev.resolve_levels_dir(tmp_path, ("m_h5_angry_birds",)) == tmp_path.resolve()
    with pytest.raises(FileNotFoundError, match="^levels_dir must be a directory"):
        klev.resolve_levels_dir(tmp_path / "missing", ("m_h5_angry_birds",))
    with pytest.raises(FileNotFoundError, match="grasp_easy.json"):
        klev.resolve_levels_dir(tmp_path, ("m_h5_angry_birds", "grasp_easy"))


def test_padding_to_the_benchmark_sizes_keeps_the_level():
    """K-21: m_h5_angry_birds (6 polygons, 3 circles, 2 joints, 2 thrusters in its file) padded to 12/4/6/2:
    the file's shapes keep their values in the first slots, every added slot is inactive, and joint indices
    (all below 6, so nothing to shift) are unchanged; @own keeps the file's sizes."""
    raw = _raw("m_h5_angry_birds")["static_env_params"]
    own = klev.load_level("m_h5_angry_birds@own")
    pad = klev.load_level("m_h5_angry_birds")
    n_poly, n_circ, n_joint = raw["num_polygons"], raw["num_circles"], raw["num_joints"]
    assert own.polygon.position.shape == (n_poly, 2) == (6, 2)
    assert pad.polygon.position.shape == (12, 2) and pad.circle.position.shape == (4, 2)
    assert pad.joint.a_index.shape == (6,) and pad.thruster.object_index.shape == (2,)
    np.testing.assert_array_equal(np.asarray(pad.polygon.position)[:n_poly], np.asarray(own.polygon.position))
    np.testing.assert_array_equal(np.asarray(pad.circle.radius)[:n_circ], np.asarray(own.circle.radius))
    assert not np.asarray(pad.polygon.active)[n_poly:].any() and not np.asarray(pad.circle.active)[n_circ:].any()
    assert not np.asarray(pad.joint.active)[n_joint:].any()
    np.testing.assert_array_equal(np.asarray(pad.joint.a_index)[:n_joint], np.asarray(own.joint.a_index))
    static = klev.level_static_env_params("m_h5_angry_birds@own")
    assert (static.num_polygons, static.num_circles, static.num_joints, static.num_thrusters) == (6, 3, 2, 2)
    assert klev.level_static_env_params("m_h5_angry_birds") == klev.benchmark_static_env_params()


def test_level_keys_are_stable_integers():
    """K-22: the benchmark's 12 keep their position; a package level folds in the first 4 bytes of SHA-256 of
    its name, big-endian, masked to 31 bits (computed here with hashlib); @own is another level."""
    assert [klev.level_index(n) for n in klev.LEVEL_NAMES] == list(range(12))
    for name in ("m_h5_angry_birds", "m_h5_angry_birds@own", "s_h4_thrust_aim"):
        want = int(hashlib.sha256(name.encode("utf-8")).hexdigest()[:8], 16) % 2**31
        assert klev.level_index(name) == want
    assert klev.level_index("m_h5_angry_birds") != klev.level_index("m_h5_angry_birds@own")
    with pytest.raises(ValueError, match="^level_name must be one of"):
        klev.level_index("nope")


def test_levels_command_and_commands_accept_package_names(capsys, tmp_path, restore_cache):
    """K-20, KE-12: `softrtc kinetix levels` lists the 12 and every package name with its sizes; a command
    given an unknown name exits 2 with the one error, naming the option and the levels command; a package
    name passes the level check of the commands."""
    from softrtc.cli import main

    assert main(["kinetix", "levels"]) == 0
    out = capsys.readouterr().out
    assert "grasp_easy, catapult" in out
    row = next(line for line in out.splitlines() if line.split()[:1] == ["m_h5_angry_birds"])
    assert row.split()[1:] == ["6", "3", "2", "2"]
    assert all(f"  {n} " in out for n in klev.package_level_names())
    assert main(["kinetix", "train-expert", "--levels", "m_h5_angry_birds,nope", "--out", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("softrtc kinetix train-expert: error: --levels entry must be one of")
    assert "`softrtc kinetix levels`; got 'nope'" in err
    # The package name passes the level check, so the error is the screen's next one (its delays).
    assert main(["kinetix", "screen", "--levels", "m_h5_angry_birds", "--out", str(tmp_path / "b"),
                 "--delays", "1,2"]) == 2
    assert capsys.readouterr().err.startswith("softrtc kinetix screen: error: delays must be increasing")
