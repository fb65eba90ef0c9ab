//! The lab's ranking is a total order and its variants are told apart by configuration.
//!
//! 1. `analysis::rank_order` (how `lab diagnose` ranks moves and `lab add` picks a variant) is
//!    fed near-tied candidates — keys within a hair of the 0.002 tie band, equal keys, ΔBIC
//!    and parameter counts in every order — and must be a total order: antisymmetric and
//!    transitive on every triple, so a sort never panics ("user-provided comparison function
//!    does not correctly implement a total order") and gives one answer for any input order.
//! 2. A model whose guide's angular term turns about the wrong axis (`about=y` where the
//!    machine's is a yaw about z) is offered the swap, and `lab add
//!    'guide_straightness:axis=x,about=z'` is a swap, not refused "already in the model".

use proptest::prelude::*;
use scancorr_core::effects::{guide_straightness, EffectConfig};
use scancorr_core::lab::analysis::{self, rank_order, Move, RankItem};
use scancorr_core::lab::dataset::{Dataset, LabPoint, Phase};
use scancorr_core::lab::program::{FeatureKind, FeatureSpec};
use scancorr_core::sample::{Axis, PointContext, Vec3};
use scancorr_core::Calibration;
use std::cmp::Ordering;

const NAMES: [&str; 4] = ["a", "b", "servo_gain", "accel_deflection:full"];

/// A near-tied candidate: a key at 1 + m·0.001 (+ a hair), so many pairs are within the tie
/// band of each other and chains of them are not.
fn item() -> impl Strategy<Value = (bool, f64, f64, usize, usize)> {
    (
        any::<bool>(),
        0u32..8,
        prop_oneof![Just(0.0), Just(1e-12), Just(-1e-12), -1e-4..1e-4],
        prop_oneof![Just(-5.0), Just(0.0), Just(5.0), -50.0..50.0],
        0usize..4,
        0usize..4,
    )
        .prop_map(|(sig, m, hair, bic, k, n)| (sig, 1.0 + m as f64 * 0.001 + hair, bic, k, n))
}

fn ri(x: &(bool, f64, f64, usize, usize)) -> RankItem<'static> {
    RankItem {
        significant: x.0,
        key: x.1,
        delta_bic: x.2,
        k: x.3,
        name: NAMES[x.4],
        replaces: None,
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(200))]
    #[test]
    fn the_ranking_is_a_total_order(v in proptest::collection::vec(item(), 3..24)) {
        let items: Vec<RankItem> = v.iter().map(ri).collect();
        for a in &items {
            prop_assert_eq!(rank_order(a, a), Ordering::Equal);
            for b in &items {
                prop_assert_eq!(rank_order(a, b), rank_order(b, a).reverse());
                for c in &items {
                    if rank_order(a, b) != Ordering::Greater
                        && rank_order(b, c) != Ordering::Greater
                    {
                        prop_assert_ne!(
                            rank_order(a, c),
                            Ordering::Greater,
                            "not transitive: {:?} ≤ {:?} ≤ {:?}", a, b, c
                        );
                    }
                }
            }
        }
        // One answer whatever the input order.
        let mut fwd = items.clone();
        fwd.sort_by(rank_order);
        let mut rev: Vec<RankItem> = items.iter().rev().cloned().collect();
        rev.sort_by(rank_order);
        prop_assert_eq!(&fwd, &rev);
        // Significant moves first.
        let first_insig = fwd.iter().position(|x| !x.significant).unwrap_or(fwd.len());
        prop_assert!(fwd[first_insig..].iter().all(|x| !x.significant));
    }
}

/// Keys in one near-tie are ranked by the information criterion, keys far apart by the key.
#[test]
fn near_ties_go_to_the_information_criterion_and_clear_wins_to_the_key() {
    let a = (true, 1.0000, 10.0, 3, 0);
    let b = (true, 1.0005, -10.0, 3, 1);
    let c = (true, 1.0100, -50.0, 3, 2);
    assert_eq!(
        rank_order(&ri(&b), &ri(&a)),
        Ordering::Less,
        "near-tie: ΔBIC"
    );
    assert_eq!(
        rank_order(&ri(&a), &ri(&c)),
        Ordering::Less,
        "clear win: key"
    );
    let d = (false, 0.5, -100.0, 1, 3);
    assert_eq!(
        rank_order(&ri(&c), &ri(&d)),
        Ordering::Less,
        "significant first"
    );
}

/// A straightedge along x (normal −y) scanned twice, nothing to fit but the geometry.
fn straightedge(cal: Calibration) -> Dataset {
    let n = Vec3::new(0.0, -1.0, 0.0);
    let mut points = vec![];
    for pass in 0..2u32 {
        for j in 0..400 {
            let x = 250.0 + 500.0 * j as f64 / 399.0;
            let nominal = Vec3::new(x, 600.0, -250.0);
            let mut ctx = PointContext::at_rest(nominal);
            ctx.deflection = n * 0.3;
            ctx.deflection_probe = n * 0.3;
            ctx.segment_id = pass;
            let dev = 1e-4 * ((j * 7 + pass as usize * 3) % 11) as f64 / 11.0;
            points.push(LabPoint {
                ctx,
                surface: nominal + n * dev,
                normal: n,
                feature: 0,
                segment: pass,
                bag: 0,
                speed: 20.0,
                direction: 0,
                phase: Phase::Steady,
                held_out: pass == 1,
            });
        }
    }
    Dataset {
        points,
        features: vec![(
            0,
            FeatureSpec {
                id: 1,
                artifact: "straightedge".into(),
                kind: FeatureKind::Face,
                nominal_center: [500.0, 600.0, -250.0],
                nominal_diameter_mm: 0.0,
                certificate_diameter_mm: None,
                normal: n.into(),
            },
        )],
        sensors: Default::default(),
        noise_floor_um: 0.1,
        tracking: vec![],
        calibration: cal,
        warnings: vec![],
    }
}

#[test]
fn a_guide_about_the_wrong_axis_is_offered_the_swap_and_lab_add_accepts_the_right_one() {
    let plain = straightedge(Calibration::example("m1"));
    let wrong = match analysis::candidate("guide_straightness:axis=x,about=y", &plain).unwrap() {
        EffectConfig::GuideStraightness(g) => g,
        other => panic!("a guide, got {}", other.kind()),
    };
    assert_eq!(wrong.pitch_about, Some(Axis::Y));
    let right = analysis::candidate("guide_straightness:axis=x,about=z", &plain).unwrap();
    // Same parameter names, different variants.
    assert_eq!(
        EffectConfig::GuideStraightness(wrong.clone()).param_names(),
        right.param_names()
    );
    assert_ne!(
        analysis::variant_key(&EffectConfig::GuideStraightness(wrong.clone())),
        analysis::variant_key(&right)
    );
    // Its knots follow the data; another knot count is the same variant.
    let mut fewer = guide_straightness::Config::zeros(Axis::X, 250.0, 750.0, 5, true);
    fewer.pitch_about = Some(Axis::Y);
    assert_eq!(
        analysis::variant_key(&EffectConfig::GuideStraightness(fewer)),
        analysis::variant_key(&EffectConfig::GuideStraightness(wrong.clone()))
    );

    let mut cal = Calibration::example("m1");
    cal.effects
        .push(EffectConfig::GuideStraightness(wrong.clone()));
    let ds = straightedge(cal);
    let moves = analysis::moves(&ds, &ds.calibration.effects);
    let swap = moves
        .iter()
        .find(|m| m.effect == "guide_straightness:axis=x,about=z")
        .expect("the swap to about=z is offered");
    assert_eq!(swap.action, Move::Swap);
    assert_eq!(swap.replaces.as_deref(), Some("guide_straightness"));
    assert!(
        !moves
            .iter()
            .any(|m| m.effect == "guide_straightness:axis=x,about=y" && m.action != Move::Drop),
        "the variant in the model is not offered again"
    );
    // `lab add 'guide_straightness:axis=x,about=z'`: a swap, not refused.
    let named = analysis::moves_named(&ds, "guide_straightness:axis=x,about=z").unwrap();
    assert_eq!(named.len(), 1);
    assert_eq!(named[0].action, Move::Swap);
    // … and made: the model's guide now turns about z.
    let applied = analysis::apply(&ds, named, false).unwrap();
    let guides: Vec<&guide_straightness::Config> = applied
        .effects
        .iter()
        .filter_map(|e| match e {
            EffectConfig::GuideStraightness(g) => Some(g),
            _ => None,
        })
        .collect();
    assert_eq!(guides.len(), 1, "one guide along x after the swap");
    assert_eq!(guides[0].pitch_about, Some(Axis::Z));
    // The variant in the model is refused by name, as before.
    let again = analysis::moves_named(&ds, "guide_straightness:axis=x,about=y");
    assert!(again.is_err(), "{again:?}");
}
