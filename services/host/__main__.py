"""``python -m services.host`` (see services.host.app)."""

import sys

from .app import main, parse_args

if __name__ == "__main__":
    sys.exit(main(parse_args()))
