"""Read parquet files with pyarrow (an independent reader of KIWI's exports) and print, as JSON,
each file's schema (column name -> arrow type string), its key-value metadata keys and its
columns as Python lists. Used by backend/tests/export.rs.

Usage: python3 read_parquet.py FILE.parquet [FILE.parquet ...]
Exit status 3 when pyarrow is not installed (the test then skips with a message)."""
import json
import sys

try:
    import pyarrow.parquet as pq
except ImportError:
    print("pyarrow is not installed (make deps installs it)", file=sys.stderr)
    sys.exit(3)

out = {}
for path in sys.argv[1:]:
    table = pq.read_table(path)
    entry = {
        "schema": {f.name: str(f.type) for f in table.schema},
        "metadata": sorted(k.decode() for k in (table.schema.metadata or {})),
        "columns": {name: table.column(name).to_pylist() for name in table.column_names},
    }
    try:
        import pandas  # noqa: F401

        df = pq.read_table(path).to_pandas()
        entry["pandas_index"] = [str(v) for v in df.index]
    except ImportError:
        pass
    out[path] = entry
json.dump(out, sys.stdout)
