"""Estimators several methods share: ray marching of segments, line gathering, density estimation, nearest-neighbour heaps and point trees."""
