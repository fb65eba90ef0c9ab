use super::*;

/// The data sheet's travel holds every program's carriage path and arc centres at its
/// usual place, and the single-artifact programs' at the place the README and the tests
/// move artifacts to (`--position` moves the whole campaign, not one artifact).
#[test]
fn every_program_stays_within_the_data_sheets_travel() {
    let m = TrueMachine::from_seed(1);
    for name in program::PROGRAMS {
        let moved = (name != "campaign").then(|| V3::new(550.0, 300.0, -250.0));
        for position in [None, moved] {
            let plan = program::plan(name, &m, position).unwrap();
            let mut t = 0.0;
            while t <= plan.duration() {
                let i = plan.segment_at(t);
                let s = &plan.segments[i];
                let check = |p: V3, what: &str| {
                    for (k, [lo, hi]) in TRAVEL_MM.iter().enumerate() {
                        assert!(
                            (*lo..=*hi).contains(&p[k]),
                            "{name} at {position:?}: {what} {p:?} outside the travel at t = {t} s"
                        );
                    }
                };
                check(s.at(t - plan.starts[i]), "carriage");
                if let Path::Arc { center, .. } = s.path {
                    check(center, "arc centre");
                }
                t += 0.01;
            }
        }
    }
}

#[test]
fn the_data_sheet_and_catalogue_make_a_valid_nominal_calibration() {
    let m = TrueMachine::from_seed(7);
    let d = data_sheet(&m, "m1", 0.001);
    let c = stylus_catalogue();
    let (cal, _) = scancorr_core::datasheet::nominal(None, Some(&d), &c, None, "").unwrap();
    // The stated time constants are 30 % off the truth's.
    let truth = calibration_for(&m, "m1", &BTreeMap::new(), &[], 0.001);
    let tau = |tf: &TransferFunction| match tf {
        TransferFunction::FirstOrder { tau_s } => *tau_s,
        _ => panic!("{tf:?}"),
    };
    assert_eq!(
        tau(&cal.nominal.axes.y),
        tau(&truth.nominal.axes.y) * DATA_SHEET_TAU_FACTOR
    );
    assert_eq!(cal.nominal.probes, truth.nominal.probes);
    // The catalogue's styli, not the machine's own.
    assert_eq!(cal.geometry.tips.len(), m.styli.len());
    for (t, s) in cal.geometry.tips.iter().zip(&m.styli) {
        assert_eq!((t.id, t.beta1_deg), (s.id, s.beta1_deg));
        assert_ne!(t.l1_mm, s.l1_mm);
    }
}
