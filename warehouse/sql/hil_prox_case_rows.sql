-- Proximity hardware-in-the-loop run: one row per image (size, truth, error), in image order.
SELECT * EXCLUDE (run)
FROM hil_prox_cases
WHERE run = $run
ORDER BY case_id;
