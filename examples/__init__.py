"""Worked examples (`examples.goal_reach`), importable from the repository's root. A regular
package rather than a namespace one, so that it wins over other `examples` packages that come
later on Python's path."""
