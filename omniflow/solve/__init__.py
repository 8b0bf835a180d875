"""The flow at the matches: the pooled solver and what it adds to eq. (16).

- :mod:`omniflow.solve.at_matches` sample, solve, refine: the flow step of the pipeline
- :mod:`omniflow.solve.gridpool` pools as filters on a grid
- :mod:`omniflow.solve.gain` a brightness gain per pool
- :mod:`omniflow.solve.decoupled` where eq. (14) fails: each unit's radial flow alone
- :mod:`omniflow.solve.refine` a Gauss-Newton step where a surface moves far
- :mod:`omniflow.solve.shading` shading flattened for the flow step
- :mod:`omniflow.solve.monocular` cam1-only flow where stereo has no match
"""
