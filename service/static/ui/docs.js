// Swagger UI of /docs, from the swagger-ui-dist npm package served by pmvir (no CDN).
window.ui = SwaggerUIBundle({
  url: "/openapi.json",
  dom_id: "#swagger-ui",
  deepLinking: true,
  persistAuthorization: false,
  validatorUrl: null, // no badge from validator.swagger.io: nothing leaves the server
});
