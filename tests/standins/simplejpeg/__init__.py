"""A stand-in for simplejpeg, which Picamera2 imports at start-up (picamera2.encoders.jpeg_encoder).

With SIMPLEJPEG_STANDIN_BUILT_FOR=numpy1 it behaves like apt's python3-simplejpeg on Raspberry Pi OS
Bookworm, a Cython extension built against Debian's numpy 1.24: under numpy 1.x it imports; under
numpy 2 its import fails as the real one's does (raspberrypi/picamera2 issues 1088, 1170, 1211):
by default with Cython's `ValueError: numpy.dtype size changed ...`; with
SIMPLEJPEG_STANDIN_FAILURE=import_array the way an extension calling numpy's import_array() fails
(numpy writes its explanation to stderr, then `ImportError: numpy.core.multiarray failed to import`).
With SIMPLEJPEG_STANDIN_BUILT_FOR=numpy2 it is a pip wheel built for numpy 2 that a numpy 1.x venv
cannot load (numpy 1.x's words: "module compiled against ABI version 0x2000000 but this version of
numpy is 0x1000009", then the ImportError). Unset, it imports everywhere (built for the numpy in use).
"""

import os
import sys

import numpy

if os.environ.get("SIMPLEJPEG_STANDIN_BUILT_FOR") == "numpy1" and int(numpy.__version__.split(".")[0]) >= 2:
    if os.environ.get("SIMPLEJPEG_STANDIN_FAILURE") == "import_array":
        sys.stderr.write(f"\nA module that was compiled using NumPy 1.x cannot be run in\nNumPy {numpy.__version__} "
                         "as it may crash. To support both 1.x and 2.x\nversions of NumPy, modules must be "
                         "compiled with NumPy 2.0.\n\nTraceback (most recent call last):\n  ...\n"
                         "AttributeError: _ARRAY_API not found\n")
        raise ImportError("numpy.core.multiarray failed to import")
    raise ValueError("numpy.dtype size changed, may indicate binary incompatibility. Expected 96 from C header, "
                     "got 88 from PyObject")

if os.environ.get("SIMPLEJPEG_STANDIN_BUILT_FOR") == "numpy2" and int(numpy.__version__.split(".")[0]) < 2:
    sys.stderr.write("RuntimeError: module compiled against ABI version 0x2000000 but this version of numpy is "
                     "0x1000009\n")
    raise ImportError("numpy.core.multiarray failed to import")


def encode_jpeg(*args, **kwargs):
    raise NotImplementedError("stand-in: no JPEG encoding")
