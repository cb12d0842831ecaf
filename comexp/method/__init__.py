"""The method, free of any simulator or experiment: frames and units (`frames`), polygon
geometry, perception from a depth image (`observation`, `tracking`, `rendering`), and the
estimators (`estimator`: the paper's Algorithms 1 and 2, the robot's library; `motion_estimator`;
`estimators`: every estimator by name, plug-ins, the factory)."""
