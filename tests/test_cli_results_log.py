"""dit_jax.cli.results_log: the --pairs results file is a log that is read, appended to and locked, never cut."""

import json
import multiprocessing

from dit_jax.cli import results_log


def test_lines_that_do_not_parse_are_skipped_by_number_and_a_cut_line_is_left_alone(tmp_path):
    """A blank line, a stray word and a record cut short: the records around them are read, the stray word's
    line is numbered (a blank one holds nothing), the file's bytes are never changed, and the next record starts a line of its own."""
    path = tmp_path / "r.jsonl"
    good = [json.dumps({"index": k}) for k in range(4)]
    text = "\n".join([good[0], "", good[1], "oops", good[2], good[3][:5]])
    path.write_text(text)
    with results_log.ResultsFile(str(path)) as log:
        assert [r["index"] for r in log.read_new()] == [0, 1, 2]
        assert log.bad_lines == [4] and log.cut_short
        assert path.read_text() == text
        log.append({"index": 9})
        assert log.read_new() == [{"index": 9}] and log.bad_lines == [4, 6]
    assert path.read_text() == text + "\n" + json.dumps({"index": 9}) + "\n"


def test_identity_follows_the_files_and_a_finished_record_is_one_with_a_level(tmp_path):
    a, b = tmp_path / "a.ply", tmp_path / "b.ply"
    a.write_text("x")
    b.write_text("yy")
    first = results_log.identity(str(a), str(b))
    assert first["src_file"][0] == 1 and first["tgt_file"][0] == 2
    a.write_text("changed")
    assert results_log.identity(str(a), str(b)) != first
    assert results_log.identity(str(tmp_path / "none.ply"), str(b))["src_file"] == [None, None]
    record = {"pair": first, "settings": {"checkpoint": None}, "level": "probably wrong"}
    assert results_log.finished(record) and not results_log.finished({"pair": first, "error": "unreadable"})
    reordered = dict(reversed(list(first.items())))
    assert results_log.identity_key(reordered) == results_log.identity_key(first)


def _hold(path: str, index: int, started, release) -> None:
    with results_log.ResultsFile(path) as log, log.pair_lock(index, wait=True):
        started.set()
        release.wait(30)


def test_a_pair_locked_by_another_process_is_not_taken_and_a_dead_holder_frees_it(tmp_path):
    """Another process holds pair 3: this one cannot take it without waiting, can take pair 4, and may append
    meanwhile (its own descriptor keeps its locks: closing none drops them). When the holder ends, pair 3 is
    free."""
    path = str(tmp_path / "r.jsonl")
    context = multiprocessing.get_context("spawn")
    started, release = context.Event(), context.Event()
    holder = context.Process(target=_hold, args=(path, 3, started, release))
    holder.start()
    try:
        assert started.wait(60)
        with results_log.ResultsFile(path) as log:
            with log.pair_lock(3, wait=False) as mine:
                assert not mine
            with log.pair_lock(4, wait=False) as mine:
                assert mine
                log.append({"index": 4})
                log.read_new()
                with log.pair_lock(3, wait=False) as still:
                    assert not still
            release.set()
            holder.join(60)
            with log.pair_lock(3, wait=False) as mine:
                assert mine
    finally:
        release.set()
        holder.join(60)
