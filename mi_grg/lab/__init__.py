"""Scripted experiments: the suite of cases (suite), the paper's experiments as run plans
(plan), the curve-logging methods they add (curves), the resumable runner (runner) here or
on a Dask cluster (cluster), and the report written from their results (report)."""
