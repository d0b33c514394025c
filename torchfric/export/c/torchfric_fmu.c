/* An FMI 2.0 FMU (Model Exchange and Co-Simulation) around a model that torchfric identified.
 *
 * The model's own functions come from torchfric_model.c, which torchfric generates from the
 * same torch code its simulator runs: tf_step (one solver step), tf_field (the vector field),
 * tf_friction (the friction torque at a state), tf_substeps (the simulator's sub-step rule) and,
 * for LuGre models, tf_bristle (the steady bristle deflection), with the parameter array p.
 *
 * Value references: 0 u, 1 q, 2 qdot, 3 friction, 4 der(q), 5 der(qdot), 6 z, 7 der(z) (LuGre),
 * 8 q0, 9 qdot0, 10 + i the model's parameter i. Written for torchfric. */
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <string.h>

#include "torchfric_fmi2.h"
#include "torchfric_model.c"

#define VR_U 0
#define VR_Q 1
#define VR_QDOT 2
#define VR_FRICTION 3
#define VR_DER 4 /* 4, 5 and (LuGre) 7 */
#define VR_Z 6
#define VR_DER_Z 7
#define VR_Q0 8
#define VR_QDOT0 9
#define VR_P 10

typedef enum { ST_INSTANTIATED, ST_INIT, ST_RUNNING, ST_TERMINATED, ST_ERROR } tf_state;

typedef struct {
  fmi2Type type;
  tf_state state;
  const fmi2CallbackFunctions *cb;
  char name[128];
  int logging;
  double time;
  double u;
  double x[TF_NX];
  double q0, qdot0;
  double p[TF_NP];
  double step_H; /* the last communication step and its sub-step count (the rule scans the */
  int step_S;    /* friction's slope): valid until a parameter changes (step_H = 0) */
} tf_instance;

static void tf_log(tf_instance *m, fmi2Status status, const char *category, const char *fmt, ...) {
  char msg[512];
  va_list ap;
  if (!m->cb || !m->cb->logger) return;
  if (status == fmi2OK && !m->logging) return;
  va_start(ap, fmt);
  vsnprintf(msg, sizeof msg, fmt, ap);
  va_end(ap);
  m->cb->logger(m->cb->componentEnvironment, m->name, status, category, "%s", msg);
}

static fmi2Status tf_fail(tf_instance *m, const char *fmt, const char *what) {
  tf_log(m, fmi2Error, "logStatusError", fmt, what);
  return fmi2Error;
}

/* Parameters a simulation can run with: finite, and a positive inertia. */
static int tf_parameters_ok(tf_instance *m) {
  for (int i = 0; i < TF_NP; ++i)
    if (!isfinite(m->p[i])) {
      tf_log(m, fmi2Error, "logStatusError", "parameter %s is not finite: give it a finite value",
             TF_PARAM_NAMES[i]);
      return 0;
    }
  if (!(m->p[TF_INERTIA] > 0.0)) {
    tf_log(m, fmi2Error, "logStatusError", "inertia must be positive, got %g", m->p[TF_INERTIA]);
    return 0;
  }
  return 1;
}

static void tf_reset(tf_instance *m) {
  m->state = ST_INSTANTIATED;
  m->time = 0.0;
  m->u = 0.0;
  m->q0 = 0.0;
  m->qdot0 = 0.0;
  memcpy(m->p, TF_PARAM_START, sizeof m->p);
  m->step_H = 0.0;
  m->step_S = 0;
  for (int i = 0; i < TF_NX; ++i) m->x[i] = 0.0;
}

static void tf_initial_state(tf_instance *m) {
  m->x[0] = m->q0;
  m->x[1] = m->qdot0;
#if TF_NX == 3
  tf_bristle(&m->qdot0, m->p, &m->x[2]);
#endif
}

static int tf_is_state(fmi2ValueReference vr, int *index) {
  if (vr == VR_Q || vr == VR_QDOT) { *index = (int)vr - VR_Q; return 1; }
#if TF_NX == 3
  if (vr == VR_Z) { *index = 2; return 1; }
#endif
  return 0;
}

static int tf_is_derivative(fmi2ValueReference vr, int *index) {
  if (vr == VR_DER || vr == VR_DER + 1) { *index = (int)vr - VR_DER; return 1; }
#if TF_NX == 3
  if (vr == VR_DER_Z) { *index = 2; return 1; }
#endif
  return 0;
}

/* ---- common functions ---- */

TF_EXPORT const char *fmi2GetTypesPlatform(void) { return "default"; }
TF_EXPORT const char *fmi2GetVersion(void) { return "2.0"; }

TF_EXPORT fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType,
                                        fmi2String fmuGUID, fmi2String fmuResourceLocation,
                                        const fmi2CallbackFunctions *functions,
                                        fmi2Boolean visible, fmi2Boolean loggingOn) {
  tf_instance *m;
  (void)fmuResourceLocation;
  (void)visible;
  if (!functions || !functions->allocateMemory || !functions->freeMemory) return NULL;
  if (!fmuGUID || strcmp(fmuGUID, TF_GUID) != 0) {
    if (functions->logger)
      functions->logger(functions->componentEnvironment, instanceName, fmi2Error,
                        "logStatusError", "the GUID %s is not this FMU's (%s)",
                        fmuGUID ? fmuGUID : "(none)", TF_GUID);
    return NULL;
  }
  m = (tf_instance *)functions->allocateMemory(1, sizeof(tf_instance));
  if (!m) return NULL;
  m->type = fmuType;
  m->cb = functions;
  m->logging = loggingOn;
  snprintf(m->name, sizeof m->name, "%s", instanceName ? instanceName : "torchfric");
  tf_reset(m);
  return m;
}

TF_EXPORT void fmi2FreeInstance(fmi2Component c) {
  tf_instance *m = (tf_instance *)c;
  if (m) m->cb->freeMemory(m);
}

TF_EXPORT fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean loggingOn,
                                         size_t nCategories, const fmi2String categories[]) {
  (void)nCategories;
  (void)categories;
  ((tf_instance *)c)->logging = loggingOn;
  return fmi2OK;
}

TF_EXPORT fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean toleranceDefined,
                                         fmi2Real tolerance, fmi2Real startTime,
                                         fmi2Boolean stopTimeDefined, fmi2Real stopTime) {
  (void)toleranceDefined;
  (void)tolerance;
  (void)stopTimeDefined;
  (void)stopTime;
  ((tf_instance *)c)->time = startTime;
  return fmi2OK;
}

TF_EXPORT fmi2Status fmi2EnterInitializationMode(fmi2Component c) {
  tf_instance *m = (tf_instance *)c;
  m->state = ST_INIT;
  tf_initial_state(m);
  return fmi2OK;
}

TF_EXPORT fmi2Status fmi2ExitInitializationMode(fmi2Component c) {
  tf_instance *m = (tf_instance *)c;
  if (!tf_parameters_ok(m)) { m->state = ST_ERROR; return fmi2Error; }
  tf_initial_state(m);
  m->state = ST_RUNNING;
  return fmi2OK;
}

TF_EXPORT fmi2Status fmi2Terminate(fmi2Component c) {
  ((tf_instance *)c)->state = ST_TERMINATED;
  return fmi2OK;
}

TF_EXPORT fmi2Status fmi2Reset(fmi2Component c) {
  tf_reset((tf_instance *)c);
  return fmi2OK;
}

TF_EXPORT fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                 fmi2Real value[]) {
  tf_instance *m = (tf_instance *)c;
  double dx[TF_NX];
  int i, have_dx = 0;
  for (size_t k = 0; k < nvr; ++k) {
    fmi2ValueReference r = vr[k];
    if (r == VR_U) value[k] = m->u;
    else if (tf_is_state(r, &i)) value[k] = m->x[i];
    else if (tf_is_derivative(r, &i)) {
      if (!have_dx) tf_field(m->x, &m->u, m->p, dx); /* once, and only when asked for */
      have_dx = 1;
      value[k] = dx[i];
    }
    else if (r == VR_FRICTION) tf_friction(m->x, &m->u, m->p, &value[k]);
    else if (r == VR_Q0) value[k] = m->q0;
    else if (r == VR_QDOT0) value[k] = m->qdot0;
    else if (r >= VR_P && r < VR_P + TF_NP) value[k] = m->p[r - VR_P];
    else {
      char ref[32];
      snprintf(ref, sizeof ref, "%u", r);
      return tf_fail(m, "fmi2GetReal: no variable has value reference %s", ref);
    }
  }
  return fmi2OK;
}

TF_EXPORT fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                 const fmi2Real value[]) {
  tf_instance *m = (tf_instance *)c;
  for (size_t k = 0; k < nvr; ++k) {
    fmi2ValueReference r = vr[k];
    if (r == VR_U) m->u = value[k];
    else if ((r == VR_Q0 || r == VR_QDOT0) && m->state != ST_INSTANTIATED && m->state != ST_INIT)
      return tf_fail(m, "%s is the initial state: set it before initialization",
                     r == VR_Q0 ? "q0" : "qdot0");
    else if (r == VR_Q0) m->q0 = value[k];
    else if (r == VR_QDOT0) m->qdot0 = value[k];
    else if (r >= VR_P && r < VR_P + TF_NP) {
      m->p[r - VR_P] = value[k];
      m->step_H = 0.0;
    } else {
      char ref[32];
      snprintf(ref, sizeof ref, "%u", r);
      return tf_fail(m, "fmi2SetReal: value reference %s is not an input or a parameter", ref);
    }
  }
  if (m->state == ST_RUNNING && !tf_parameters_ok(m)) return fmi2Error;
  return fmi2OK;
}

#define TF_NO_VALUES(NAME, TYPE)                                                             \
  TF_EXPORT fmi2Status NAME(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,      \
                            TYPE value[]) {                                                  \
    (void)vr;                                                                                \
    (void)value;                                                                             \
    return nvr ? tf_fail((tf_instance *)c, "%s: this FMU has Real variables only", #NAME)    \
               : fmi2OK;                                                                     \
  }
TF_NO_VALUES(fmi2GetInteger, fmi2Integer)
TF_NO_VALUES(fmi2GetBoolean, fmi2Boolean)
TF_NO_VALUES(fmi2GetString, fmi2String)
TF_NO_VALUES(fmi2SetInteger, const fmi2Integer)
TF_NO_VALUES(fmi2SetBoolean, const fmi2Boolean)
TF_NO_VALUES(fmi2SetString, const fmi2String)

#define TF_UNSUPPORTED(NAME, ARGS)                                                           \
  TF_EXPORT fmi2Status NAME ARGS {                                                           \
    return tf_fail((tf_instance *)c, "%s is not supported by this FMU", #NAME);              \
  }
TF_UNSUPPORTED(fmi2GetFMUstate, (fmi2Component c, fmi2FMUstate *s))
TF_UNSUPPORTED(fmi2SetFMUstate, (fmi2Component c, fmi2FMUstate s))
TF_UNSUPPORTED(fmi2FreeFMUstate, (fmi2Component c, fmi2FMUstate *s))
TF_UNSUPPORTED(fmi2SerializedFMUstateSize, (fmi2Component c, fmi2FMUstate s, size_t *n))
TF_UNSUPPORTED(fmi2SerializeFMUstate, (fmi2Component c, fmi2FMUstate s, fmi2Byte b[], size_t n))
TF_UNSUPPORTED(fmi2DeSerializeFMUstate,
               (fmi2Component c, const fmi2Byte b[], size_t n, fmi2FMUstate *s))
TF_UNSUPPORTED(fmi2GetDirectionalDerivative,
               (fmi2Component c, const fmi2ValueReference a[], size_t na,
                const fmi2ValueReference b[], size_t nb, const fmi2Real dv[], fmi2Real df[]))
TF_UNSUPPORTED(fmi2SetRealInputDerivatives,
               (fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                const fmi2Integer order[], const fmi2Real value[]))
TF_UNSUPPORTED(fmi2GetRealOutputDerivatives,
               (fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                const fmi2Integer order[], fmi2Real value[]))
TF_UNSUPPORTED(fmi2CancelStep, (fmi2Component c))
TF_UNSUPPORTED(fmi2GetStatus, (fmi2Component c, const fmi2StatusKind s, fmi2Status *value))
TF_UNSUPPORTED(fmi2GetIntegerStatus,
               (fmi2Component c, const fmi2StatusKind s, fmi2Integer *value))
TF_UNSUPPORTED(fmi2GetBooleanStatus,
               (fmi2Component c, const fmi2StatusKind s, fmi2Boolean *value))
TF_UNSUPPORTED(fmi2GetStringStatus, (fmi2Component c, const fmi2StatusKind s, fmi2String *value))

TF_EXPORT fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *value) {
  if (s != fmi2LastSuccessfulTime)
    return tf_fail((tf_instance *)c, "%s: only fmi2LastSuccessfulTime is known",
                   "fmi2GetRealStatus");
  *value = ((tf_instance *)c)->time;
  return fmi2OK;
}

/* ---- Co-Simulation: the simulator's steps, u held over the communication step ---- */

TF_EXPORT fmi2Status fmi2DoStep(fmi2Component c, fmi2Real currentCommunicationPoint,
                                fmi2Real communicationStepSize,
                                fmi2Boolean noSetFMUStatePriorToCurrentPoint) {
  tf_instance *m = (tf_instance *)c;
  double H = communicationStepSize;
  (void)noSetFMUStatePriorToCurrentPoint;
  if (m->state != ST_RUNNING) return tf_fail(m, "%s before initialization ended", "fmi2DoStep");
  if (!(H > 0.0)) return tf_fail(m, "fmi2DoStep: the step size must be positive%s", "");
  if (H != m->step_H) {
    m->step_S = tf_substeps(H, m->p);
    m->step_H = H;
  }
  tf_advance(m->x, m->u, currentCommunicationPoint, H, m->step_S, m->p);
  for (int j = 0; j < TF_NX; ++j)
    if (!isfinite(m->x[j])) {
      m->state = ST_ERROR;
      tf_log(m, fmi2Error, "logStatusError",
             "the state is no longer finite at t = %g: the simulation diverged (check the "
             "parameters and the input)", currentCommunicationPoint + H);
      return fmi2Error;
    }
  m->time = currentCommunicationPoint + H;
  return fmi2OK;
}

/* ---- Model Exchange: the field, for the importer's solver ---- */

TF_EXPORT fmi2Status fmi2EnterEventMode(fmi2Component c) { (void)c; return fmi2OK; }

TF_EXPORT fmi2Status fmi2NewDiscreteStates(fmi2Component c, fmi2EventInfo *info) {
  (void)c;
  info->newDiscreteStatesNeeded = fmi2False;
  info->terminateSimulation = fmi2False;
  info->nominalsOfContinuousStatesChanged = fmi2False;
  info->valuesOfContinuousStatesChanged = fmi2False;
  info->nextEventTimeDefined = fmi2False;
  info->nextEventTime = 0.0;
  return fmi2OK;
}

TF_EXPORT fmi2Status fmi2EnterContinuousTimeMode(fmi2Component c) { (void)c; return fmi2OK; }

TF_EXPORT fmi2Status fmi2CompletedIntegratorStep(fmi2Component c,
                                                 fmi2Boolean noSetFMUStatePriorToCurrentPoint,
                                                 fmi2Boolean *enterEventMode,
                                                 fmi2Boolean *terminateSimulation) {
  (void)c;
  (void)noSetFMUStatePriorToCurrentPoint;
  *enterEventMode = fmi2False;
  *terminateSimulation = fmi2False;
  return fmi2OK;
}

TF_EXPORT fmi2Status fmi2SetTime(fmi2Component c, fmi2Real time) {
  ((tf_instance *)c)->time = time;
  return fmi2OK;
}

TF_EXPORT fmi2Status fmi2SetContinuousStates(fmi2Component c, const fmi2Real x[], size_t nx) {
  tf_instance *m = (tf_instance *)c;
  if (nx != TF_NX) return tf_fail(m, "fmi2SetContinuousStates: this model has %s states", TF_NX_TEXT);
  for (size_t j = 0; j < nx; ++j) m->x[j] = x[j];
  return fmi2OK;
}

TF_EXPORT fmi2Status fmi2GetDerivatives(fmi2Component c, fmi2Real dx[], size_t nx) {
  tf_instance *m = (tf_instance *)c;
  if (nx != TF_NX) return tf_fail(m, "fmi2GetDerivatives: this model has %s states", TF_NX_TEXT);
  tf_field(m->x, &m->u, m->p, dx);
  return fmi2OK;
}

TF_EXPORT fmi2Status fmi2GetEventIndicators(fmi2Component c, fmi2Real z[], size_t ni) {
  (void)z;
  return ni ? tf_fail((tf_instance *)c, "%s: this model has no event indicators",
                      "fmi2GetEventIndicators")
            : fmi2OK;
}

TF_EXPORT fmi2Status fmi2GetContinuousStates(fmi2Component c, fmi2Real x[], size_t nx) {
  tf_instance *m = (tf_instance *)c;
  if (nx != TF_NX) return tf_fail(m, "fmi2GetContinuousStates: this model has %s states", TF_NX_TEXT);
  for (size_t j = 0; j < nx; ++j) x[j] = m->x[j];
  return fmi2OK;
}

TF_EXPORT fmi2Status fmi2GetNominalsOfContinuousStates(fmi2Component c, fmi2Real x_nominal[],
                                                       size_t nx) {
  (void)c;
  for (size_t j = 0; j < nx; ++j) x_nominal[j] = TF_NOMINALS[j];
  return fmi2OK;
}
