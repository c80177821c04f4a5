"""Watching a cell over time: a judged reference scan checked against its certified sphere (body of the node's
``~/reference``) and the drift monitor (EWMA + CUSUM on reference residuals and interval coverage).

May import: scan.
"""
