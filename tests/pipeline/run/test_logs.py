"""The log file of a command that runs Prefect or Dask: records and tracebacks to
``OUT/logs/``, not the terminal; errors leave the block naming the file."""

from __future__ import annotations

import io
import logging

import pytest

from mscal_core.errors import FrameError, UnexpectedError
from pipeline.run.logs import command_log


@pytest.fixture
def console():
    """A logger that does not propagate and prints to a console stream, like Prefect's and Dask's."""
    stream = io.StringIO()
    stream.name = "<stderr>"
    handler = logging.StreamHandler(stream)
    lg = logging.getLogger("fake_prefect_internal")
    lg.propagate, lg.level = False, logging.INFO
    lg.addHandler(handler)
    yield lg, stream
    lg.handlers.clear()


def test_records_and_tracebacks_go_to_the_file_not_the_console(tmp_path, console) -> None:
    lg, stream = console
    with pytest.raises(FrameError) as info, command_log(tmp_path, "run") as path:
        lg.info("Starting temporary server")
        raise FrameError("unreadable image", path="a.tif")
    assert stream.getvalue() == ""
    assert path.parent == tmp_path / "logs" and path.name.endswith("-run.log")
    assert info.value.log_file == str(path)
    text = path.read_text()
    assert "Starting temporary server" in text and "Traceback" in text and "a.tif: unreadable image" in text
    lg.info("after the block")  # the console handler stays off: no line after the command's last
    assert stream.getvalue() == "" and "after the block" not in path.read_text()


def test_verbose_keeps_the_console(tmp_path, console) -> None:
    lg, stream = console
    with command_log(tmp_path, "serve", verbose=True) as path:
        lg.info("a task finished")
    assert "a task finished" in stream.getvalue() and "a task finished" in path.read_text()


def test_an_unexpected_error_is_one_line_naming_the_log(tmp_path) -> None:
    with pytest.raises(UnexpectedError) as info, command_log(tmp_path, "run") as path:
        {}["missing"]
    err = info.value
    assert err.exit_code == 1 and err.log_file == str(path) and "\n" not in str(err)
    assert str(err).startswith("unexpected error: KeyError: 'missing'")
    assert "Traceback" in path.read_text() and "KeyError" in path.read_text()
