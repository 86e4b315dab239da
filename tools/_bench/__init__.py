"""Helpers only the benchmark tools use (operator counting, GEMM rates); the engine never imports them. The tools
run as scripts from tools/, which puts this package on the import path."""
