"""Running SLAM: the algorithm over one shared map (`slam`: SLAM, its one per-frame method
`process`), what feeds it frames (`runner`: sequential, or real time with an input clock and the
`workers` beside tracking; `handover`: a keyframe's work beside tracking), the I/O around it
(`pipeline`: building the roles and running the phases; `state`: what the run has produced so
far; `outputs`: its files; `metrics`: metrics.json and the summary line; `frame_log`:
frames.csv), input read-ahead (`prefetch`), the viewer feed (`viewing`) and returning free heap
memory (`heap`)."""
