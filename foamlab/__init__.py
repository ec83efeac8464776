"""foamlab: compression testing of flexible foam.

Run data, the paper's combined model (polynomial elastic + hereditary damping +
fractional residual force), identification, diagnosis, acquisition and storage.
"""

__version__ = "0.1.0"

from pathlib import Path

#: Repository folder holding machine profiles, methods and specimens (TOML).
CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"


class FoamlabError(Exception):
    """An error the user can act on; the CLI prints it as one line and exits non-zero."""
