"""Running SLAM: the loop over one shared map (`slam`: SLAM, MappingThread), the I/O around it
(`pipeline`: building the roles and running them; `state`: what the run has produced so far;
`outputs`: its files; `metrics`: metrics.json and the summary line; `frame_log`: frames.csv),
input read-ahead (`prefetch`), the viewer feed (`viewing`) and returning free heap memory
(`heap`)."""
