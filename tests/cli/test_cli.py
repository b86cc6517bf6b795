"""The command line rejects bad input in one line before any work starts ([N-7]); tests that run nothing heavy."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from softrtc import _cli_util as cu
from softrtc.cli import main

ROOT = Path(__file__).resolve().parents[2]


def status(argv):
    try:
        return main(argv)
    except SystemExit as exc:  # argparse: usage, then one error line
        return exc.code


def last_error_line(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    return err.strip().splitlines()[-1]


def test_argument_types_name_the_range():
    """N-7: the shared argument types reject what they must, with the allowed range in the message."""
    import argparse

    assert cu.int_in("x", 1, 3)("2") == 2 and cu.real_in("x", 0.0, 1.0)("0.5") == 0.5
    for bad, parse in (("0", cu.int_in("x", 1, 3)), ("2.5", cu.int_in("x", 1, 3)), ("nan", cu.real_in("x", 0, 1)),
                       ("inf", cu.real_in("x")), ("", cu.nonempty()), ("1,,2", cu.comma_list("x", int)),
                       ("2,", cu.comma_list("x", int)), ("1,1", cu.comma_list("x", int)), ("", cu.output_file()),
                       ("", cu.output_dir()), ("", cu.input_dir())):
        with pytest.raises(argparse.ArgumentTypeError):
            parse(bad)
    with pytest.raises(argparse.ArgumentTypeError, match=r"in \[1, 3\], got 0"):
        cu.int_in("x", 1, 3)("0")
    assert cu.comma_list("x", int, unique=False)("1,1") == [1, 1]
    with pytest.raises(argparse.ArgumentTypeError, match=r"in \(0.0, 1.0\], got '0'"):
        cu.real_in("x", 0.0, 1.0, lo_open=True)("0")
    assert cu.real_in("x", 0.0, 1.0, lo_open=True)("1") == 1.0


def test_output_and_input_paths_are_checked_up_front(tmp_path):
    """N-7, N-11: an output that cannot be written is an error before the work, not after it."""
    import argparse

    f = tmp_path / "afile"
    f.write_text("x")
    assert cu.output_file()(str(tmp_path / "new" / "deeper" / "r.json")) == str(tmp_path / "new" / "deeper" / "r.json")
    assert cu.output_dir()(str(tmp_path / "new")) == str(tmp_path / "new")
    for parse, bad in ((cu.output_file(), str(tmp_path)), (cu.output_file(), str(f / "x.json")),
                       (cu.output_dir(), str(f)), (cu.input_dir(), str(f)), (cu.input_dir(), str(tmp_path / "none"))):
        with pytest.raises(argparse.ArgumentTypeError):
            parse(bad)
    assert not (tmp_path / "new").exists()  # checking creates nothing
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]  # nor leaves a scratch file behind
    # A folder whose permission bits allow writing but which takes no files (root passes os.access on /proc).
    if Path("/proc").is_dir():
        import os

        # Root passes the permission bits, so only the scratch file shows that /proc takes no files.
        why = "does not take new files" if os.access("/proc", os.W_OK | os.X_OK) else "not a writable directory"
        with pytest.raises(argparse.ArgumentTypeError, match=f"cannot be written: /proc {why}|/proc is {why}"):
            cu.output_file()("/proc/softrtc-report.json")


@pytest.mark.parametrize("argv, word", [
    (["weights", "--H", "0"], "--H"),
    (["weights", "--H", "2000000000", "--s", "1"], "--H"),
    (["weights", "--lam", "nan"], "--lam"),
    (["weights", "--rule", "hard", "--lam", "3"], "--lam does not apply to --rule hard"),
    (["weights", "--rule", "fixed", "--h-max", "3"], "--h-max does not apply to --rule fixed"),
    (["weights", "--H", "9", "--h-max", "12"], "--h-max must be <= --H=9, got 12"),
    (["weights", "--H", "4", "--s", "2"], "--h-max must be <= --H=4, got 5 (the default"),
    (["weights", "--H", "4", "--s", "2", "--rule", "fixed", "--length", "6"], "--length must be <= --H=4"),
    (["weights", "--s", "9"], "--s must be an integer in [1, 8] (--H), got 9"),
    (["weights", "--H", "1_0"], "--H"),
    (["weights", "--H", "\uff18"], "--H"),
    (["bench", "runtime", "--calls", "2.5"], "--calls: value must be an integer in [1, 10000000]"),
    (["bench", "vjp", "--seed", "1e3"], "--seed: value must be an integer in [0, 2147483647]"),
    (["bench", "runtime", "--train-calls", "nan"], "--train-calls"),
    (["bench", "runtime", "--steps", "1001"], "--steps"),
    (["conformance", "generate", "--out", ""], "--out"),
    (["conformance", "generate", "--out", "README.md"], "--out"),
    (["conformance", "run", "--impl", "reference", "--only", "nosuch"], "'nosuch' is not an interface function"),
    (["conformance", "run", "--impl", "reference", "--only", ","], "--only"),
    (["conformance", "run", "--impl", "reference", "--vectors", "README.md"], "is not a directory"),
    (["conformance", "run", "--impl", "reference", "--report", ""], "--report"),
    (["bench", "runtime", "--batch-sizes", "1,,2"], "--batch-sizes"),
    (["bench", "vjp", "--out", "softrtc"], "--out"),
    (["arm", "study", "--max-steps", "2000"], "--max-steps"),
    (["arm", "study", "--latency-ms", "-5"], "--latency-ms"),
    (["arm", "study", "--trials", "20000"], "--trials"),
    (["arm", "study", "--checkpoints", "/nonexistent"], "--checkpoints"),
    (["arm", "study", "--out", "README.md"], "--out"),
    (["arm", "train", "--seed", "2147483647"], "--seed"),
    (["arm", "train", "--steps", "0"], "integer in [1, 10000000], got 0"),
    (["arm", "expert", "--seed0", "99999999999999999999"], "--seed0"),
])
def test_bad_options_exit_2_with_one_line(argv, word, capsys):
    """N-7, N-11, CF-19, B-10: each bad option exits with status 2 and names itself; no traceback."""
    assert status(argv) == 2
    line = last_error_line(capsys)
    assert line.startswith("softrtc ") and word in line, line


def test_malformed_vector_files_are_one_line_errors(tmp_path, capsys):
    """CF-2, CF-16: a vector file of the wrong structure stops the run with a message naming file and case."""
    for text, word in (("[1]", "expected a JSON object"), ('{"format_version": "1.0", "cases": [5]}', "case 0"),
                       ('{"format_version": "1.0", "cases": [{"id": "E.x.y", "function": "endpoint", '
                        '"requirements": 5, "args": {}, "tolerance": {}, "expected": {}}]}', "'requirements'")):
        (tmp_path / "a.json").write_text(text)
        assert status(["conformance", "run", "--impl", "reference", "--vectors", str(tmp_path)]) == 2
        line = last_error_line(capsys)
        assert "a.json" in line and word in line, line


def test_groups_without_a_subcommand_print_help_and_exit_2(capsys):
    """N-11: `softrtc arm`, `kinetix`, `bench`, `conformance` alone are usage errors (status 2): the usage line and
    one error line saying a subcommand is needed go to standard error, nothing to standard output."""
    for group in ("arm", "kinetix", "bench", "conformance"):
        assert status([group]) == 2
        cap = capsys.readouterr()
        assert cap.out == ""
        assert cap.err.startswith("usage: softrtc " + group)
        assert f"softrtc {group}: error: a subcommand is needed" in cap.err


def test_library_errors_become_one_line(monkeypatch, capsys):
    """N-11: a ValueError or OSError from a command ends as `softrtc CMD: error: ...`, status 2, no traceback;
    SOFTRTC_TRACEBACK=1 shows the traceback."""
    import softrtc.reference_cli as rcli

    def boom():
        raise OSError("disk full")

    monkeypatch.setattr(rcli, "demo", boom)
    assert status(["examples"]) == 2
    assert last_error_line(capsys) == "softrtc examples: error: disk full"
    monkeypatch.setenv("SOFTRTC_TRACEBACK", "1")
    with pytest.raises(OSError, match="disk full"):
        main(["examples"])


def test_python_m_conformance_names_itself():
    """CF-19: `python -m softrtc.conformance` shows its own name once in the usage line."""
    out = subprocess.run([sys.executable, "-m", "softrtc.conformance", "run", "--help"], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.startswith("usage: python -m softrtc.conformance run ")
    res = subprocess.run([sys.executable, "-m", "softrtc.conformance", "run", "--impl", "reference", "--only",
                          "endpoint"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and res.stdout.splitlines()[-1].startswith("PASS: "), res.stdout + res.stderr


def test_conformance_report_is_written(tmp_path):
    """CF-14: --report writes JSON into a directory it creates."""
    out = tmp_path / "sub" / "r.json"
    assert status(["conformance", "run", "--impl", "reference", "--only", "endpoint", "--report", str(out)]) == 0
    assert json.loads(out.read_text())["counts"]["fail"] == 0


@pytest.mark.parametrize("argv, prog", [
    (["weights", "--H", "4", "--s", "2"], "softrtc weights"),
    (["bench", "runtime", "--calls", "0"], "softrtc bench runtime"),
    (["bench", "vjp", "--execute-horizon", "9"], "softrtc bench vjp"),
    (["conformance", "run", "--impl", "nosuch_adapter_module"], "softrtc conformance run"),
    (["conformance", "generate", "--out", "README.md"], "softrtc conformance generate"),
    (["arm", "study", "--checkpoints", "/nonexistent"], "softrtc arm study"),
    (["weights", "--bogus"], "softrtc weights"),
    (["bench", "runtime", "--bogus", "3"], "softrtc bench runtime"),
])
def test_every_error_line_names_the_whole_command(argv, prog, capsys):
    """N-11, CF-18: bad options, library errors and unknown options all end in one line that starts with the
    whole command, `softrtc CMD SUB: error: `, and exit with status 2."""
    assert status(argv) == 2
    line = last_error_line(capsys)
    assert line.startswith(prog + ": error: "), line


@pytest.mark.parametrize("argv, exc", [
    (["weights", "--H", "4", "--s", "2"], ValueError),
    (["bench", "runtime", "--execute-horizon", "9", "--arch", "tiny"], ValueError),
    (["conformance", "run", "--impl", "nosuch_adapter_module"], Exception),
])
def test_traceback_switch_reraises_in_every_command(argv, exc, monkeypatch):
    """N-11: with SOFTRTC_TRACEBACK=1 an error inside any command is re-raised with its traceback, including the
    commands that report their own errors (weights, bench, conformance)."""
    monkeypatch.setenv("SOFTRTC_TRACEBACK", "1")
    with pytest.raises(exc):
        main(argv)


@pytest.mark.parametrize("argv, names", [
    ([], "demo, weights, examples, conformance, bench, arm, kinetix"),
    (["conformance"], "run, generate, report, rollout"),
    (["bench"], "runtime, vjp, table, torch"),
    (["arm"], "train, study, expert, mechanism, experiment, screen, report, torch"),
    (["kinetix"], "eval, finetune, bench, levels, report, train-expert, generate-data, train-bc, screen"),
])
def test_a_command_group_alone_is_a_usage_error(argv, names, capsys):
    """N-11: `softrtc` without a command, and each command group without its subcommand, is a usage error as
    argparse reports one: nothing on stdout, the usage line and one error line naming the subcommands on
    stderr, status 2; `--help` prints the help on stdout with status 0."""
    prog = " ".join(["softrtc"] + argv)
    assert status(argv) == 2
    out, err = capsys.readouterr()
    assert out == ""
    lines = err.splitlines()
    assert lines[0].startswith(f"usage: {prog} [-h] ")
    assert lines[-1] == f"{prog}: error: a subcommand is needed (one of: {names})"
    assert status(argv + ["--help"]) == 0
    out, err = capsys.readouterr()
    assert out.startswith(f"usage: {prog} ") and err == ""


def test_integer_options_take_plain_decimals_only():
    """N-7, N-11: integer options take ASCII decimal digits with an optional sign; Python's int() would also
    read '1_0' as 10, ' 7' as 7 and full-width digits."""
    import argparse

    parse = cu.int_in("value", -5, 100)
    assert parse("10") == 10 and parse("-3") == -3 and parse("+4") == 4
    for bad in ("1_0", " 7", "7 ", "\uff18", "0x10", "1e1", ""):
        with pytest.raises(argparse.ArgumentTypeError, match="must be an integer"):
            parse(bad)


def test_real_options_take_plain_decimals_only(capsys):
    """N-7, N-11: real options take ASCII decimal numbers (sign, fraction, exponent); Python's float() would also
    read '1_0' as 10, ' 2 ' as 2, full-width and Arabic-Indic digits. The command names the option."""
    import argparse

    parse = cu.real_in("value", 0.0, 100.0)
    for text, want in (("2", 2.0), ("+2.5", 2.5), (".5", 0.5), ("5.", 5.0), ("1e1", 10.0), ("2.5E-1", 0.25)):
        assert parse(text) == want, text
    for bad in ("1_0", " 2", "2 ", "\uff12", "\u0663", "\uff11.5", "0x1", "1e", ".", "inf", "nan", "1e400", ""):
        with pytest.raises(argparse.ArgumentTypeError, match=r"^value must be a finite number in \[0.0, 100.0\], "
                                                             r"got "):
            parse(bad)
    for bad in ("1_0", "\uff12", " 2 "):
        assert status(["weights", "--lam", bad]) == 2
        assert last_error_line(capsys) == (f"softrtc weights: error: argument --lam: value must be a finite number "
                                           f"in [0.0, 4096.0], got {bad!r}")


def test_bench_delay_takes_rotate_or_a_plain_integer(capsys):
    """N-11, B-10: --delay is 'rotate' or an ASCII integer in [0, 4096]; '1_0', full-width digits and padding
    are errors naming --delay, where int() read them as 10, 1 and 1."""
    from softrtc.jax.cli import _delay

    assert _delay("rotate") is None and _delay("3") == 3 and _delay("0") == 0
    for bad in ("1_0", "\uff11", " 1", "1 ", "-1", "4097", "1.0", ""):
        assert status(["bench", "runtime", "--delay", bad]) == 2
        assert last_error_line(capsys) == ("softrtc bench runtime: error: argument --delay: value must be 'rotate' "
                                           f"or an integer in [0, 4096], got {bad!r}")


def test_weights_table_lines_have_no_trailing_spaces(capsys):
    """W-7: the weights table printed by `softrtc weights` has no trailing blanks (it is compared as text)."""
    assert status(["weights"]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[1].startswith("d  e(d) e* | j=0")
    assert all(line == line.rstrip() for line in out.splitlines())


def test_kinetix_methods_spelled_twice_are_one_method(tmp_path, capsys):
    """KE-2, N-11: `--methods` naming one method and window twice (bare train_soft and its explicit window, or
    lam 2 and 2.0) is an error before any rollout, not two identical rows."""
    pytest.importorskip("kinetix", reason="needs kinetix-env")
    for methods in ("train_soft,train_soft:delay_scaled:2:5", "train_soft:delay_scaled:2,train_soft:delay_scaled:2.0"):
        assert status(["kinetix", "eval", "--methods", methods, "--out", str(tmp_path / "o")]) == 2
        line = last_error_line(capsys)
        assert line.startswith("softrtc kinetix eval: error: ") and "same method and window" in line, line
    assert not (tmp_path / "o").exists()


def test_shared_output_helpers(tmp_path):
    """N-11, B-10: check_out_dir (used by every writer of a folder) accepts a folder to create and refuses a file,
    a path under a file and a folder standing where a written file goes, naming the argument; write_atomic
    leaves an existing file untouched and no temporary file behind when the writer fails."""
    from softrtc._files import check_out_dir, write_atomic

    f = tmp_path / "afile"
    f.write_text("old")
    (tmp_path / "o" / "t.md").mkdir(parents=True)
    assert check_out_dir("out", tmp_path / "new" / "deeper") == tmp_path / "new" / "deeper"
    assert not (tmp_path / "new").exists()
    for bad, word in ((f, "is a file"), (f / "x", "cannot be created"), (tmp_path / "o", "t.md"), ("", "non-empty"),
                      (5, "non-empty")):
        with pytest.raises(ValueError, match="out") as info:
            check_out_dir("out", bad, ("t.md",))
        assert word in str(info.value), info.value
    if Path("/proc").is_dir():  # permission bits may allow writing (root); the scratch file shows it does not
        with pytest.raises(ValueError, match="out /proc/softrtc-out cannot be written: /proc"):
            check_out_dir("out", "/proc/softrtc-out")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "o"]  # no scratch file left behind

    def broken(fh):
        fh.write("partial")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        write_atomic(f, broken)
    assert f.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["afile", "o"]
    write_atomic(f, lambda fh: fh.write("new"))
    assert f.read_text() == "new" and sorted(p.name for p in tmp_path.iterdir()) == ["afile", "o"]


def test_cli_stops_quietly_when_its_reader_goes_away():
    """N-11: `softrtc examples | head -1` must not end in a traceback: a closed stdout exits with 128 + SIGPIPE.

    The read end is closed before the child has imported anything, so its first write meets a closed pipe.
    """
    proc = subprocess.Popen([sys.executable, "-m", "softrtc.cli", "examples"], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 141, err
    assert "Traceback" not in err and "BrokenPipeError" not in err, err


def test_pickle_loaders_warn_that_files_must_be_trusted(capsys):
    """KE-10, P-8: every option that unpickles release policies says in its --help that unpickling can run code
    and only trusted files may be loaded; so does the Kinetix guide (docs/guides/kinetix.md)."""
    pytest.importorskip("kinetix")
    warning = "The .pkl files are unpickled, which can run code stored in them: load only files from a source " \
              "you trust."
    for argv, options in ((["kinetix", "eval", "--help"], ("--policy-dir", "--method-policy")),
                          (["kinetix", "finetune", "--help"], ("--bc",))):
        assert status(argv) == 0
        blocks, current = {}, None
        for line in capsys.readouterr().out.splitlines():
            if line.startswith("  -"):  # an option's first line; its help continues on indented lines
                current = line.split()[0]
                blocks[current] = []
            if current is not None:
                blocks[current].append(line.strip())
        for option in options:
            text = " ".join(" ".join(blocks[option]).split())  # argparse wraps lines
            assert text.endswith(warning), (option, text)
    readme = " ".join((ROOT / "docs" / "guides" / "kinetix.md").read_text().split())
    assert "so load only files from a source you trust" in readme and "unpickling can run code" in readme


@pytest.mark.parametrize("module, argv, extra", [
    ("tqdm", ["bench", "runtime", "--calls", "1"], "jax"),
    ("tqdm", ["bench", "vjp", "--calls", "1"], "jax"),
    ("matplotlib", ["arm", "report"], "arm"),
    ("matplotlib", ["arm", "study", "--trials", "1"], "arm"),
    ("tqdm", ["arm", "experiment", "--quick"], "jax"),
])
def test_a_missing_optional_module_is_one_line_naming_the_extra(module, argv, extra, tmp_path, capsys, monkeypatch):
    """N-13: a command whose optional module (tqdm for the training progress, matplotlib for the arm plots)
    is missing ends at the door with status 2 and one line naming the extra; nothing is written."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setitem(sys.modules, module, None)  # what `import` and find_spec see for an absent module
    option = {"bench": ["--out", str(tmp_path / "b.json")], "arm": []}[argv[0]]
    if argv[:2] == ["arm", "report"]:
        option = ["--results", str(tmp_path / "none")]
    if argv[:2] in (["arm", "study"], ["arm", "experiment"]):
        option = ["--out", str(tmp_path / "out")] + (["--work", str(tmp_path / "w")] if argv[1] == "experiment" else [])
    assert status(argv + option) == 2
    out, err = capsys.readouterr()
    hint = f"needs the '{extra}' extra (missing module {module}): pip install 'softrtc[{extra}]'"
    assert err.splitlines() == [f"softrtc {' '.join(argv[:2])}: error: {hint}"
                                + (" (or run with --no-plots)" if argv[1] == "report" else "")]
    assert list(tmp_path.iterdir()) == []


def test_a_module_missing_deep_inside_a_command_is_one_line_too(capsys, monkeypatch):
    """N-13: an optional module imported deep inside a command (past its door checks) still ends it with one
    line naming the extra; a module of no extra keeps its traceback (it is a defect, not a missing extra)."""
    import softrtc.reference_cli as rc

    def fail(args):
        raise ModuleNotFoundError("No module named 'tqdm.auto'; 'tqdm' is not a package", name="tqdm.auto")

    monkeypatch.setattr(rc, "_weights", fail, raising=False)
    parser = __import__("softrtc.cli", fromlist=["build_parser"]).build_parser()
    weights = parser._subparsers._group_actions[0].choices["weights"]
    monkeypatch.setattr(weights, "_defaults", dict(weights._defaults, func=fail))
    monkeypatch.setattr("softrtc.cli.build_parser", lambda: parser)
    assert status(["weights"]) == 2
    assert capsys.readouterr().err == ("softrtc weights: error: needs the 'jax' extra (missing module tqdm): "
                                       "pip install 'softrtc[jax]'\n")
    assert cu.extra_hint("not_an_extra_module") is None
    assert cu.missing_extra("json", "matplotlib.pyplot") is None
