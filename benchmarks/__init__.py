"""What the benchmark and analysis tools under ``tools/`` share, importable by the tests like any
package (a tool is a thin command over it)."""
