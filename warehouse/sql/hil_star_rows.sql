-- Star hardware-in-the-loop run: every column of every image row (SI units), in image order.
SELECT * EXCLUDE (run)
FROM hil_star
WHERE run = $run
ORDER BY case_id;
