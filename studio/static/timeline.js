// timeline editor (below)
