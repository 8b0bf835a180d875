"""Files in and out: images, JSON, the omnisim dataset format, pictures of flow.

- :mod:`omniflow.io.imageio` image files and atomic writes
- :mod:`omniflow.io.jsonio` the project's one JSON rule
- :mod:`omniflow.io.dataset` the dataset contract and its reader
- :mod:`omniflow.io.draw` flow colour coding and arrows
- :mod:`omniflow.io.ownership` what a command may delete (markers) and its output lock
"""
