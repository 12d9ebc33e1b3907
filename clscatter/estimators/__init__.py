"""Estimators several methods share: ray marching of view segments, line-space gathering,
surface density estimation over lighting rays, its kd-tree and k-nearest queries."""
