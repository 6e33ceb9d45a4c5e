"""Scripted experiments: suites of cases and methods, their run plan and runner, and the
report written from their results."""
