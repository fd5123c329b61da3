"""The annotated view between the loop's thread and the API's: asked for only while watched, each view
numbered, the count right however the watchers come and go."""

from __future__ import annotations

import threading

from clothd.outputs.view import ViewBoard


def test_the_view_is_wanted_while_watched_and_each_post_is_numbered() -> None:
    board = ViewBoard()
    assert not board.watched and board.latest() == (None, 0)
    with board.watching():
        assert board.watched
        board.post(b"one")
        board.post(b"two")
        assert board.latest() == (b"two", 2)
    assert not board.watched


def test_watchers_on_many_threads_leave_the_count_at_zero() -> None:
    board = ViewBoard()

    def watch() -> None:
        for _ in range(2000):
            with board.watching():
                pass

    threads = [threading.Thread(target=watch) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not board.watched and board._watchers == 0
