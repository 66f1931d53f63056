"""report.txt says what it means: no bare "None" settings, "p < 0.001" instead of "p = 0.000",
and a "?" in the shift grid comes with its legend."""

from __future__ import annotations

from masking_lab.commands.cli import main


def _table(path, same_cell: bool):
    rows = ["participant,target,masker,masker_level_db_sl,shift_db"]
    for i, p in enumerate(("A", "B", "C", "D")):
        for m, offset in (("MV120", 0.0), ("MV270", 6.0)):
            for x in (5, 10, 15, 20, 25):
                shift = 0.6 * x - 3 + offset + 0.13 * ((i * 7 + x) % 5)
                if same_cell and m == "MV120" and x == 5:
                    shift = 1.0  # every participant alike: the cell's t-test cannot be computed
                rows.append(f"{p},EV270,{m},{x},{shift:.3f}")
    path.write_text("\n".join(rows) + "\n")
    return path


def test_settings_p_values_and_untestable_cells_are_explained(tmp_path):
    out = tmp_path / "out"
    argv = ["fit", str(_table(tmp_path / "s.csv", True)), "--out", str(out), "--n-boot", "200"]
    assert main(argv) == 0
    text = (out / "report.txt").read_text(encoding="utf-8")
    assert "None" not in text and "p = 0.000" not in text
    assert "created_utc: 1970-01-01T00:00:00Z (fixed default" in text
    assert "pool_groups: none" in text
    assert "Bonferroni p < 0.001 → different" in text
    grid = text.split("Mean AL shift per cell")[1].split("Pooling")[0]
    assert "?1.000" in grid
    assert "? = test not computable (zero variance or one participant)" in grid


def test_no_legend_for_a_question_mark_that_is_not_there(tmp_path):
    out = tmp_path / "out"
    argv = ["fit", str(_table(tmp_path / "s.csv", False)), "--out", str(out), "--n-boot", "200"]
    assert main(argv) == 0
    grid = (out / "report.txt").read_text(encoding="utf-8").split("Mean AL shift per cell")[1]
    assert "?" not in grid.split("Pooling")[0]
