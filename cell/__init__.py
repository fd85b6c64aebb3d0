"""The tapecell cell: calibration, arm drivers, grasp planning, rerun logging, episodes
and the ``tapecell`` command. It ties ``estimator`` (images -> tape) to ``sim`` (the
MuJoCo cell) and to the real UR arm.
"""
