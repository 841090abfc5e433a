"""Benchmarks and test harnesses: integration, wire, colony, and the local colony launcher."""
