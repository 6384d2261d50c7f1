"""After the boundary moved: the interior follows, and no cell may invert.

* :mod:`~nagata_snap.smoothing.quality` -- inversion checks, mean ratio,
  angles and the per-level :class:`QualityReport` (the simplex kernels
  under them are in :mod:`nagata_snap.mesh.simplex`);
* :mod:`~nagata_snap.smoothing.band` -- the band of cells around the moved
  vertices that the smoothers work on, and ghost-consistent node masks;
* :mod:`~nagata_snap.smoothing.neighbourhood` -- the few layers around bad
  cells, distributed like the mesh (:mod:`~nagata_snap.smoothing.halo`: the
  exchanges between the copies of its shared nodes);
* :mod:`~nagata_snap.smoothing.smooth` -- the interior smoother;
* :mod:`~nagata_snap.smoothing.untangle` -- Escobar's regularised mean-ratio
  optimisation that untangles inverted cells;
* :mod:`~nagata_snap.smoothing.slide` -- boundary vertices that may slide on
  their geometry during the repair;
* :mod:`~nagata_snap.smoothing.repair` -- the guard: check, smooth, untangle,
  shorten moves, in that order.
"""

from nagata_snap.smoothing.quality import QualityReport
from nagata_snap.smoothing.repair import InvertedCellsError, RepairResult, repair
from nagata_snap.smoothing.smooth import smooth

__all__ = ["InvertedCellsError", "QualityReport", "RepairResult", "repair", "smooth"]
