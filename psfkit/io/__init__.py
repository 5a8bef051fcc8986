"""Input and output at the boundary: images, PSF grids, atomic writes."""

from psfkit.io.atomic import OutputTransaction, atomic_directory, atomic_file
from psfkit.io.grid import GridPosition, PsfGrid
from psfkit.io.grid_validation import read_grid
from psfkit.io.grid_writer import GridWriter
from psfkit.io.images import read_image, write_image
from psfkit.io.pairs import PairSet, read_pairs

__all__ = ["GridPosition", "GridWriter", "OutputTransaction", "PairSet", "PsfGrid",
           "atomic_directory",
           "atomic_file", "read_grid", "read_image", "read_pairs", "write_image"]
