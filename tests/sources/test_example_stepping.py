"""The custom stepping source example runs and prints exact sim times."""

from __future__ import annotations

from _examples import run_example


def test_custom_stepping_source_example() -> None:
    proc = run_example("custom_stepping_source.py")
    assert proc.stdout.splitlines() == [
        "0.000000000 s (sim): x = +1.000",
        "0.200000000 s (sim): x = +0.921",
        "0.400000000 s (sim): x = +0.696",
        "0.600000000 s (sim): x = +0.361",
        "600 steps in 0.600000000 s (sim)",
        "the mass came back at 3.071000000 s (sim)",
        "a sleeper was woken by the jump: -1.000000000 s",
        "restored to 3.071000000 s (sim), x = +0.990",
    ]
