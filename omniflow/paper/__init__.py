"""The paper's algorithm as written (L. Spacek, *Omni Flow*), eq. (8)-(20).

- :mod:`omniflow.paper.dct` the truncated DCT fit and its derivatives, eq. (17)-(18)
- :mod:`omniflow.paper.edges` the polar edge finder, eq. (19)-(20)
- :mod:`omniflow.paper.matching` the paper's radial matching rule, section 5.2
- :mod:`omniflow.paper.flow` the polar flow equation and its coaxial solution,
  eq. (8), (9), (15), (16)

This package imports only :mod:`omniflow.conventions`, :mod:`omniflow.geometry` and
itself (``tests/test_layout.py``): the extensions build on it, never the reverse.
"""
