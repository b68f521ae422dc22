"""Print a SHA-256 of every array of a zarr store (decoded values, dtype and shape) and of all of them.

Used to show that a change keeps a store byte-identical:
``python scripts/store_checksum.py demo/toy.zarr``. Attributes are left out (they hold the
package version and timings); arrays are compared by their decoded contents, so the
checksum does not depend on how zarr laid the chunks out.
"""

from __future__ import annotations

import hashlib
import sys

from sceneforge.store import array_digests


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print(__doc__.strip().splitlines()[0], file=sys.stderr)
        print("usage: python scripts/store_checksum.py STORE", file=sys.stderr)
        return 2
    digests = array_digests(argv[0])
    for name, digest in digests.items():
        print(f"{digest[:16]}  {name}")
    total = hashlib.sha256("".join(f"{k}={v}\n" for k, v in digests.items()).encode()).hexdigest()
    print(f"{total}  all {len(digests)} arrays")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
