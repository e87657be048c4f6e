"""Vision-navigation flight companion: camera frames in, MAVLink pose estimates out.

Math subpackages (``georef``, ``vo``, ``lba``, ``ekf``) and the modules ``geometry``, ``types``
import no I/O. I/O lives in ``companion.io``; wiring lives in ``companion.daemon``.
"""

__version__ = "0.1.0"
