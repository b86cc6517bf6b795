"""The PyTorch pages of the documentation: the guide's example runs, the reports' tables are the committed
results' ([PT-8], [PT-9])."""

from __future__ import annotations

from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

ROOT = Path(__file__).resolve().parents[2]
GUIDE = ROOT / "docs" / "guides" / "torch.md"
BENCH = (ROOT / "docs" / "reports" / "benchmarks.md", "## PyTorch benchmark")
ARM = (ROOT / "docs" / "reports" / "arm.md", "## PyTorch policies beside the JAX ones")


def _section(path: Path = GUIDE, heading: str | None = None) -> str:
    """A page, or its section from ``heading`` to the next heading of the same level."""
    text = path.read_text()
    if heading is None:
        return text
    start = text.index(heading)
    end = text.find("\n## ", start + len(heading))
    return text[start:end if end > 0 else None]


def _blocks(lang: str = "", where: tuple = (GUIDE,)) -> list:
    """The fenced blocks of a section whose opening fence names ``lang`` ("" for plain fences)."""
    blocks, current, opened = [], None, None
    for line in _section(*where).splitlines():
        if line.startswith("```"):
            if current is None:
                current, opened = [], line[3:].strip()
            else:
                if opened == lang:
                    blocks.append("\n".join(current) + "\n")
                current = None
        elif current is not None:
            current.append(line)
    return blocks


def test_readme_example_trains_and_samples():
    """[PT-4], [PT-1] The guide's example runs as written: one soft training step in flipped time (finite
    loss, gradients on every parameter) and one soft-sampler chunk of shape [1, H, A] whose weights clamp
    the first d = 3 tokens."""
    code = _blocks("python")
    assert len(code) == 1 and len(code[0].splitlines()) <= 25
    env = {}
    exec(compile(code[0], str(GUIDE), "exec"), env)
    assert torch.isfinite(env["loss"]) and env["chunk"].shape == (1, env["H"], env["A"])
    assert env["w"][:3].tolist() == [1.0, 1.0, 1.0] and float(env["w"][3]) < 1.0
    assert all(p.grad is not None for p in env["model"].parameters())


def run2_sentence(name: str = "bench_run2.json") -> str:
    """The benchmarks page's line on a committed benchmark run (the second run, or the adaln network's), from its
    file."""
    from softrtc.torch import bench

    t = {x["name"]: x for x in bench.read_json(ROOT / "results" / "torch" / name)["targets"]}
    failed = [n for n, x in t.items() if not x["passed"]]
    verdict = "all targets passed" if not failed else "failed: " + ", ".join(failed)
    return (f"{t['train-time samplers / naive, batch 1']['value']:.2f} and "
            f"{t['train-time samplers / naive, batch 32']['value']:.2f} for the training-time samplers at batch 1 "
            f"and 32, {t['soft / hard training step']['value']:.2f} soft / hard and "
            f"{t['soft / plain flow-matching step']['value']:.2f} soft / plain; {verdict}")


def test_readme_bench_table_is_the_committed_result():
    """[PT-8] The benchmark table of the benchmarks page is `softrtc bench torch --table results/torch/bench.json`, and
    its line on the second run gives that run's committed ratios."""
    from softrtc.torch import bench

    want = bench.format_table(bench.read_json(ROOT / "results" / "torch" / "bench.json"))
    assert want.strip() in [b.strip() for b in _blocks(where=BENCH)]
    assert " ".join(run2_sentence().split()) in " ".join(_section(*BENCH).split())


def test_readme_adaln_bench_line_is_the_committed_result():
    """[PT-8] The benchmarks page's line on `softrtc bench torch --architecture adaln` gives the committed run's ratios
    and names the targets it failed; the file is a run of the chapter-P network."""
    from softrtc.torch import bench

    res = bench.read_json(ROOT / "results" / "torch" / "bench_adaln.json")
    assert res["config"]["architecture"] == "adaln" and "adaln network" in bench.format_table(res)
    assert " ".join(run2_sentence("bench_adaln.json").split()) in " ".join(_section(*BENCH).split())


def test_readme_arm_table_is_the_committed_result():
    """[PT-9] The arm table of the arm results page is `softrtc arm torch --table results/torch/arm.json`: the summary
    recomputed from the committed episodes (paired: every policy ran the same env seeds at every delay)."""
    pytest.importorskip("pymunk")
    from softrtc.torch import arm

    res = arm.read_results(ROOT / "results" / "torch" / "arm.json")
    assert arm.format_table(res["summary"]).strip() in [b.strip() for b in _blocks(where=ARM)]
    seeds = {}
    for r in res["episodes"]:
        seeds.setdefault(r["policy"], set()).add((r["delay"], r["env_seed"]))
    assert len(set(map(frozenset, seeds.values()))) == 1 and len(seeds) == 6
