"""Uses of omni flow (the paper's section 6) and regions of a result.

- :mod:`omniflow.applications.navigation` time to contact, steering, position fix, odometry
- :mod:`omniflow.applications.regions` the points of an object and their summary
"""
