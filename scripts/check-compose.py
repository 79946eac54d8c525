#!/usr/bin/env python3
"""Validate deploy/docker-compose.yml against the Compose specification's JSON schema.

The schema is the one Docker Compose itself validates with (`compose/config/compose_spec.json`),
read from the `docker-compose` wheel on PyPI (downloaded, not installed, into a temporary
folder), so no Docker engine is needed. Unknown keys, wrong types and misspelt fields fail.

    python3 scripts/check-compose.py [FILE ...]
"""
import glob
import json
import os
import subprocess
import sys
import tempfile
import zipfile

import jsonschema
import yaml

HERE = os.path.dirname(os.path.abspath(__file__))


def main():
    files = sys.argv[1:] or [os.path.join(HERE, "..", "deploy", "docker-compose.yml")]
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run([sys.executable, "-m", "pip", "download", "--quiet", "--disable-pip-version-check",
                        "--no-deps", "--dest", tmp, "docker-compose==1.29.2"], check=True)
        wheel = glob.glob(os.path.join(tmp, "*.whl"))[0]
        schema = json.loads(zipfile.ZipFile(wheel).read("compose/config/compose_spec.json"))
    validator = jsonschema.Draft7Validator(schema)
    failed = False
    for path in files:
        with open(path) as f:
            doc = yaml.safe_load(f)
        errors = sorted(validator.iter_errors(doc), key=lambda e: list(e.path))
        for e in errors:
            where = "/".join(str(p) for p in e.path) or "(top)"
            print(f"{path}: {where}: {e.message}", file=sys.stderr)
        failed |= bool(errors)
        if not errors:
            print(f"{path}: valid against the Compose specification")
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
