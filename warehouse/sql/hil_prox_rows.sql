-- Proximity hardware-in-the-loop run: every column of every image x threshold row (SI units), in image and
-- threshold order (an unreadable image: one row, error set, threshold NULL).
SELECT * EXCLUDE (run)
FROM hil_prox
WHERE run = $run
ORDER BY case_id, threshold NULLS FIRST;
