"""The pose cells' actions on the experience map (OpenRatSLAM's PC_NO_ACTION, PC_CREATE_NODE,
PC_CREATE_EDGE, PC_SET_NODE), in a module of their own so that the experience map and the
odometry-bias estimator read them without importing the pose cells."""

NO_ACTION, CREATE_NODE, CREATE_EDGE, SET_NODE = 0, 1, 2, 3
