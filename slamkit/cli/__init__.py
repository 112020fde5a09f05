"""The command-line programs: `slamkit` (`main`), `slamkit-bench` (`bench`), `slamkit-report`
(`report`), `slamkit-plugins` (`plugins`) and `slamkit-export` (`export`)."""
