"""The input pipeline: what a run reads (`data_spec`), the split and checks (`dataset`), sample
selection and the curriculum (`sampling`, `curriculum`), streamed video (`video_stream`), the
per-sample transforms and the batch (`transforms`, `batching`), the grain pipeline itself
(`pipeline`), and the inputs a run records for its policy (`run_inputs`, `chunk_stats`)."""
