"""Bench section ``ledger``: the "nothing new" night over an archive whose
captures are not images (a night that read one would fail it)."""

from rsmb.pipeline.bench._bench_ledger import bench_ledger


def test_a_night_with_nothing_new_skips_every_capture_by_its_stat(tmp_path, capsys):
    figures = bench_ledger(tmp_path, count=150)
    assert figures["captures"] == 150 and figures["night"]["seconds"] > 0
    assert figures["night"]["read_chars"] > 0 and figures["ledger_bytes"] > 0
    assert "a night with nothing new over 150 done captures" in capsys.readouterr().out
