-- Calibration run (job kind calibrate): one row per photo in input order, with the board's inner corners
-- (col, row pairs, OpenCV's pixel convention) where it was found; what `dualsight calibrate` solves from.
SELECT * EXCLUDE (run)
FROM calib_views
WHERE run = $run
ORDER BY case_id;
