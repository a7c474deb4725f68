"""``python -m services.recorder``: the recorder role (see services.recorder.app)."""

import sys

from ..runtime import service_main
from .app import main, parse_args

if __name__ == "__main__":
    sys.exit(service_main(parse_args, main))
