"""The data: its formats (`formats`), its statistics (`statistics`), the input pipeline
(`pipeline`), and the vocabulary they share: episode tables (`episodes`), cameras (`cameras`),
state and action selections (`selection`), JSON files written atomically (`json_files`) and
background work (`background`)."""
