"""Dataset label formats at the edge of the package: TuSimple JSON lines, CULane .lines.txt.

Readers return plain records (dicts with "image_path" and "lanes", lanes as (N, 2) float
pixel arrays ordered by y descending, in the file's lane order); writers take the same records.
"""

from __future__ import annotations

from lanevil_train.data.formats.culane import read_culane, write_culane, write_culane_lanes
from lanevil_train.data.formats.images import image_file_problem, load_image
from lanevil_train.data.formats.tusimple import read_tusimple, write_tusimple

__all__ = ["load_image", "image_file_problem", "read_tusimple", "write_tusimple", "read_culane", "write_culane",
           "write_culane_lanes"]
