"""``python -m layerwatch``: the same program as the ``layerwatch`` script (:func:`layerwatch.cli.main`)."""

import sys

from layerwatch.cli import main

if __name__ == "__main__":
    sys.exit(main())
