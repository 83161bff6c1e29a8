"""Query algorithms: the stereo matchers whose depth maps get labelled."""
