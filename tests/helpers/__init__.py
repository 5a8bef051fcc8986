"""Helpers shared by several test files: reference models and accessors that only the tests
use (issue 44: what no product code calls left psfkit/ and ekdun/)."""
