"""Rescan planning: the search over settings and head orientations for the set-up with the lowest predicted
error in a region (body of ``~/recommend_settings``), and its verification by re-simulation in the virtual scanner
(``xmetro verify-recommend``).

May import: scan, sim, judge.
"""
