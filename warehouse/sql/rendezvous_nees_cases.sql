-- Rendezvous filter consistency per approach (issue 23, point 6 c): the NEES (6 dof) of each of the approaches with
-- case_id < $first at each frame >= $conv (after convergence) of one run ($run): how persistent the NEES is from
-- frame to frame, which sets the simultaneous band of the report (nav/nees_band.py).
SELECT case_id, frame, nees
FROM rendezvous_frames WHERE run = $run AND case_id < $first AND frame >= $conv
ORDER BY case_id, frame;
