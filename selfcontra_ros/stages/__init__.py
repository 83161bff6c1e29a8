"""The three labelling stages of the paper: support, voting, outliers."""
