"""Review D: `python -m pipeline.commands.bench`'s counts and durations are checked when parsed, a bad one a
one-line usage error (before: --epochs 0 silently ran train.max_epochs, --rounds 0 the default, --seeds 139
139 a spread of 0 over copies, --calls 5 an IndexError after starting the service, --threads -1 a
RuntimeError after the stages up to parts)."""
import pytest

from pipeline.commands.bench import __main__ as bench


@pytest.mark.parametrize("argv, said", [
    (["real", "--epochs", "0"], "--epochs: an integer >= 1, got 0"),
    (["real", "--seeds", "139", "139"], "--seeds: distinct seeds"),
    (["real", "--seeds", "-1"], "--seeds: an integer >= 0, got -1"),
    (["real", "--threads", "-1"], "--threads: an integer >= 1, got -1"),
    (["serve", "--calls", "5"], "--calls: an integer >= 10, got 5"),
    (["serve", "--clients", "0"], "--clients: an integer >= 1, got 0"),
    (["export", "--rounds", "0"], "--rounds: an integer >= 1, got 0"),
    (["speed", "--soak", "0"], "--soak: a finite number > 0, got 0"),
    (["speed", "--soak", "nan"], "--soak: a finite number > 0, got nan"),
    (["plan", "--n", "-3"], "--n: an integer >= 1, got -3"),
    (["path", "--spacings", "0"], "--spacings: a finite number > 0, got 0"),
])
def test_bad_counts_are_usage_errors_before_any_work(argv, said, capsys, monkeypatch):
    for name in ("bench_real", "bench_serve", "bench_export", "bench_speed", "bench_plan", "bench_path"):
        monkeypatch.setattr(bench, name, lambda *a, **k: pytest.fail(f"{argv} ran"))
    with pytest.raises(SystemExit) as e:
        bench.main(argv)
    assert e.value.code == 2 and said in capsys.readouterr().err
