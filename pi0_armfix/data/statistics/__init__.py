"""Statistics of the data: normalization statistics and their files (`stats`), normalization
(`normalize`), and motion per group (`motion`: arm-heavy selection, balanced statistics)."""
