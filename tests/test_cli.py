"""The command line: help, one-line red errors, a broken house among good ones."""

from __future__ import annotations

from click.testing import CliRunner
from sceneforge.cli.main import COMMANDS, cli

from sceneforge.errors import EXIT_FAILURES, EXIT_INTERRUPTED
from sceneforge.houses.formats.native import write_house


def run(*args):
    return CliRunner().invoke(cli, list(map(str, args)))


def test_help_lists_every_command():
    res = run("--help")
    assert res.exit_code == 0
    for name in COMMANDS:
        assert name in res.output


def test_inspect_prints_table_and_writes_preview(small_house, tmp_path):
    write_house(small_house, tmp_path / "houses" / "small")
    res = run("houses", "inspect", tmp_path / "houses", "--preview", tmp_path / "png")
    assert res.exit_code == 0, res.output
    assert "small" in res.output and "chair" in res.output and "1 house read, 0 failed" in res.output
    assert (tmp_path / "png" / "small.png").stat().st_size > 1000


def test_broken_house_is_one_line_and_others_complete(small_house, tmp_path):
    for name in ("a", "b"):
        small_house.id = name
        write_house(small_house, tmp_path / name)
    (tmp_path / "a" / "house.bin").unlink()
    res = run("houses", "inspect", tmp_path)
    assert res.exit_code == EXIT_FAILURES
    failed = [line for line in res.output.splitlines() if line.startswith("failed:")]
    assert len(failed) == 1 and "house a" in failed[0] and "cannot read buffer" in failed[0]
    assert "1 house read, 1 failed" in res.output
    assert "Traceback" not in res.output


def test_expected_error_is_one_red_line(tmp_path):
    res = run("houses", "inspect", tmp_path / "missing")
    assert res.exit_code == 1
    assert res.output.strip().splitlines() == [f"error: {tmp_path / 'missing'}: no such file or folder"]


def test_ctrl_c_says_how_to_resume(monkeypatch, tmp_path):
    import sceneforge.pipeline

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(sceneforge.pipeline, "render_dataset", interrupted)
    res = run("render", "bundled:toy", tmp_path / "out.zarr")
    assert res.exit_code == EXIT_INTERRUPTED
    assert res.output.strip().splitlines() == ["interrupted: run the same command again to resume"]


def test_an_early_error_is_the_only_line_no_blank_line_before_it(tmp_path):
    # the progress bar appears with the first step: a command refused before it prints no empty bar line
    cases = [
        (("render", tmp_path / "nothing", tmp_path / "o.zarr"), "no such file or folder"),
        (("reconstruct", tmp_path / "run", tmp_path / "photos", tmp_path / "out"), ""),
        (("predict", tmp_path, tmp_path / "none.zarr", tmp_path / "p.zarr"), ""),
        (("train", tmp_path / "none.zarr", "--stage", "depth", "--run", tmp_path / "r"), ""),
    ]
    for args, words in cases:
        res = run(*args)
        assert res.exit_code in (1, 2), (args, res.output)
        lines = res.output.splitlines()
        if res.exit_code == 1:
            assert len(lines) == 1 and lines[0].startswith("error: ") and words in lines[0], (args, res.output)


def test_typos_get_a_suggestion(tmp_path):
    res = run("rendr", "bundled:toy", tmp_path / "o.zarr")
    assert res.exit_code == 2 and "No such command 'rendr'. Did you mean 'render'?" in res.output
    res = run("houses", "inspect", "bundled:toyy")
    assert res.exit_code == 1
    assert res.output.splitlines() == ["error: bundled:toyy: no such file or folder (did you mean bundled:toy?)"]
    (tmp_path / "kitchen").mkdir()
    res = run("houses", "inspect", tmp_path / "kitchn")
    assert res.output.splitlines() == [
        f"error: {tmp_path / 'kitchn'}: no such file or folder (did you mean {tmp_path / 'kitchen'}?)"]
