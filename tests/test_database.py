"""database.py: the only database io, importable without torch (a tool that only reads a database
loads no network)."""

import contextlib
import re
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from colmap_guided import database as dbio
from colmap_guided.__main__ import main
from colmap_guided.log import set_verbosity


def test_database_io_imports_no_torch():
    code = (
        "import sys, colmap_guided.database, colmap_guided.verify, "
        "colmap_guided.image_data; assert 'torch' not in sys.modules, 'torch imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_no_module_but_database_py_calls_pycolmap_database(tmp_path):
    """Every read and write of the COLMAP database goes through colmap_guided/database.py."""
    from pathlib import Path

    import colmap_guided

    package = Path(colmap_guided.__file__).parent
    calls = (
        "Database.open",
        "DatabaseTransaction",
        "db.read_",
        "db.write_",
        "db.exists_",
        "db.num_",
        "db.clear_",
        "db.delete_",
    )
    offenders = [
        f"{path.relative_to(package)}: {call}"
        for path in sorted(package.rglob("*.py"))
        if path.name != "database.py"
        for call in calls
        if call in path.read_text(encoding="utf-8")
    ]
    assert offenders == []


OUR_ERROR = re.compile(r"^\[[\d:]+ colmap_guided ERROR\] (.+)$", re.M)
# Another program's write transaction on the database, open until this process's stdin closes.
HOLD_LOCK = (
    "import sqlite3, sys; c = sqlite3.connect(sys.argv[1], isolation_level=None); "
    "c.execute('BEGIN IMMEDIATE'); print('locked', flush=True); sys.stdin.read()"
)


def _match_cli(database: Path, capfd) -> tuple[int, str]:
    """`python -m colmap_guided match` in this process; returns its exit code and its one error
    line."""
    (database.parent / "images").mkdir(exist_ok=True)
    try:
        code = main(
            [
                "match",
                "--database_path",
                str(database),
                "--image_path",
                str(database.parent / "images"),
            ]
        )
    finally:
        set_verbosity(False, False)
    err = capfd.readouterr().err
    assert "Traceback" not in err and len(OUR_ERROR.findall(err)) == 1, err
    return code, OUR_ERROR.findall(err)[0]


def _library_errors(database: Path) -> list[str]:
    """The messages of open_database (must exist, or not) and remove_orphans on ``database``."""
    messages = []
    for call in (
        lambda: dbio.open_database(database),
        lambda: dbio.open_database(database, must_exist=False),
    ):
        with pytest.raises(dbio.DatabaseError) as err, call():
            pass
        messages.append(str(err.value))
    with pytest.raises(dbio.DatabaseError) as err:
        dbio.remove_orphans(database)
    return [*messages, str(err.value)]


@pytest.mark.parametrize(
    "case, says",
    [
        ("corrupt", "not a COLMAP database, or a damaged one"),
        ("foreign", "an SQLite file without COLMAP's tables"),
        ("empty", "an empty file, not a COLMAP database"),
    ],
)
def test_a_file_that_is_not_a_colmap_database_is_one_line_and_left_as_it_is(
    tmp_path, capfd, case, says
):
    """Random bytes, another program's SQLite database, an empty file: one line naming the file and
    what to do, from the library and the CLI (exit 2); the file's bytes unchanged, nothing beside
    it."""
    database = tmp_path / "database.db"
    if case == "corrupt":
        database.write_bytes(
            np.random.default_rng(0).integers(0, 256, 8192, dtype=np.uint8).tobytes()
        )
    elif case == "foreign":
        with contextlib.closing(sqlite3.connect(database)) as conn, conn:
            conn.execute("CREATE TABLE letters (sender TEXT, body TEXT)")
            conn.execute("INSERT INTO letters VALUES ('archive', 'a note')")
    else:
        database.write_bytes(b"")
    before = database.read_bytes()
    code, line = _match_cli(database, capfd)
    for message in [line, *_library_errors(database)]:
        assert "\n" not in message and str(database) in message and says in message
        assert "pass another --database_path or a new --output" in message
    assert code == 2
    assert database.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == [
        "database.db",
        "images",
    ]


def test_a_database_locked_by_another_program_is_one_line_and_left_as_it_is(
    tmp_path, capfd, monkeypatch
):
    """Another program writing to the database: one line saying so (library and CLI), nothing
    written; once it is done the same database works (its orphan camera removed)."""
    database = tmp_path / "database.db"
    with dbio.open_database(
        database, must_exist=False
    ) as db:  # a camera without images: remove_orphans writes
        dbio.write_camera(
            db,
            pycolmap.Camera(model="PINHOLE", width=80, height=60, params=[90.0, 90.0, 40.0, 30.0]),
        )
    before = database.read_bytes()
    monkeypatch.setattr(dbio, "BUSY_TIMEOUT_S", 0.5)
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD_LOCK, str(database)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "locked"
        code, line = _match_cli(database, capfd)
        errors = [line, *_library_errors(database)]
    finally:
        holder.stdin.close()
        holder.wait(timeout=60)
    assert code == 2
    for message in errors:
        assert (
            "\n" not in message
            and str(database) in message
            and "is locked by another program" in message
        )
    assert database.read_bytes() == before
    assert dbio.remove_orphans(database) == (1, 0)


# Another program reading the database, one short connection after another, for ARGV[2] seconds.
READ_IN_A_LOOP = (
    "import sqlite3, sys, time; end = time.time() + float(sys.argv[2]); uri = sys.argv[1]\n"
    "print('reading', flush=True)\n"
    "while time.time() < end:\n"
    "    c = sqlite3.connect(uri, uri=True, timeout=5); c.execute('SELECT COUNT(*) FROM images')\n"
    "    c.close()"
)


def test_colmap_opening_the_database_while_another_program_reads_it_waits(tmp_path):
    """COLMAP opens a database with no busy timeout: a reader's connection closing at that moment
    (the last one checkpoints the WAL) fails about 1 open in 100; every open here succeeds."""
    database = tmp_path / "database.db"
    with dbio.open_database(database, must_exist=False):
        pass
    reader = subprocess.Popen(
        [sys.executable, "-c", READ_IN_A_LOOP, f"{database.as_uri()}?mode=ro", "4"],
        stdout=subprocess.PIPE,
        text=True,
    )
    opened = 0
    try:
        assert reader.stdout.readline().strip() == "reading"
        while reader.poll() is None:
            with dbio.open_database(database) as db:
                opened += db.num_images() == 0
    finally:
        reader.wait(timeout=60)
    assert reader.returncode == 0 and opened > 300


def test_no_module_but_database_py_opens_sqlite(tmp_path):
    """Plain SQLite connections (remove_orphans, the checks) are database.py's too, behind its
    one-line errors."""
    import colmap_guided

    package = Path(colmap_guided.__file__).parent
    assert [
        p.name for p in sorted(package.rglob("*.py")) if "sqlite3" in p.read_text(encoding="utf-8")
    ] == ["database.py"]
