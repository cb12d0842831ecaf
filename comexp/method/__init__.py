"""The method, free of any simulator or experiment: frames and units (`scene`), polygon
geometry, perception from a depth image (`observation`, `tracking`, `rendering`; `perception`
re-exports them), and the estimator (the paper's Algorithms 1 and 2)."""
