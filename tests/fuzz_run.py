"""Feed damaged inputs to the readers, one JSON line per case (run by tests/test_fuzz.py).

A separate process, so that a native crash of a reader is seen as the process dying while
a case was being read (the last "start" line names it) instead of killing the test run.
Usage: ``python tests/fuzz_run.py CASES.json`` where the file lists [path, kind] pairs.
"""

from __future__ import annotations

import json
import sys
import traceback
import warnings


def main(list_file: str) -> None:
    from core.io import DataFileError, load_mesh, load_model, load_points, load_volume
    from core.session import document as session

    loaders = {"mesh": load_mesh, "volume": load_volume, "points": load_points,
               "model": load_model, "session": session.load_session}
    with open(list_file, encoding="utf-8") as fh:
        cases = json.load(fh)
    out = sys.stdout
    for index, (path, kind) in enumerate(cases):
        out.write(json.dumps({"start": index}) + "\n")
        out.flush()
        result: dict = {"index": index}
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                loaders[kind](path)
                result["status"] = "loaded"
            except DataFileError as exc:
                result["status"] = "refused"
                result["message"] = str(exc)
            except BaseException as exc:  # noqa: BLE001 - every other outcome is a defect
                result["status"] = "exception"
                result["message"] = "".join(traceback.format_exception_only(exc)).strip()
        result["warnings"] = [str(w.message) for w in caught]
        out.write(json.dumps(result) + "\n")
        out.flush()


if __name__ == "__main__":
    main(sys.argv[1])
