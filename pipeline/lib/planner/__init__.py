"""The measurement planner: coverage of a program, the D-criterion, the order to measure in."""
