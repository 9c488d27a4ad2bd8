"""database.py: the only database io, importable without torch (a tool that only reads a database loads no network)."""

import subprocess
import sys


def test_database_io_imports_no_torch():
    code = "import sys, colmap_guided.database, colmap_guided.verify, colmap_guided.image_data; assert 'torch' not in sys.modules, 'torch imported'"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_no_module_but_database_py_calls_pycolmap_database(tmp_path):
    """Every read and write of the COLMAP database goes through colmap_guided/database.py."""
    from pathlib import Path

    import colmap_guided

    package = Path(colmap_guided.__file__).parent
    calls = ("Database.open", "DatabaseTransaction", "db.read_", "db.write_", "db.exists_", "db.num_", "db.clear_", "db.delete_")
    offenders = [
        f"{path.relative_to(package)}: {call}"
        for path in sorted(package.rglob("*.py"))
        if path.name != "database.py"
        for call in calls
        if call in path.read_text(encoding="utf-8")
    ]
    assert offenders == []
