"""Recorded pushes of real objects: the reader of their logs and the estimators run on them."""
